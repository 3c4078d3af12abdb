"""Against a real Ray head on 127.0.0.1 started by cluster/start-head.sh (token auth, own ports and temp dir):
`ray job submit`, a worker killed mid-run, evaluation fan-out, and the Ray Data read path."""
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import free_ports, short_tmpdir
from roken.data.store import read_run

pytestmark = pytest.mark.slow  # a real local Ray cluster

ROOT = Path(__file__).resolve().parents[1]
PYBIN = str(Path(sys.executable).parent)


@pytest.fixture(scope="module")
def head():
    gcs, dash, client, agent = free_ports(4)
    head_dir = short_tmpdir("rkh")
    env = {**os.environ, "RAY_HEAD_DIR": head_dir, "RAY_PORT": str(gcs), "RAY_DASHBOARD_PORT": str(dash),
           "RAY_CLIENT_PORT": str(client), "RAY_AUTH_TOKEN_PATH": os.path.join(head_dir, "token"),
           "RAY_AUTH_MODE": "token", "PYTHON": sys.executable, "PATH": PYBIN + os.pathsep + os.environ["PATH"]}
    env.pop("RAY_ADDRESS", None)
    t0 = time.time()
    r = subprocess.run(["bash", str(ROOT / "cluster" / "start-head.sh"), "--num-cpus=2",
                        f"--dashboard-agent-listen-port={agent}"], env=env, capture_output=True, text=True,
                       timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    env["START_SECONDS"] = f"{time.time() - t0:.1f}"
    env["GCS"] = f"127.0.0.1:{gcs}"
    env["JOBS"] = f"http://127.0.0.1:{dash}"
    yield env
    # a test cluster need not drain: what is still up after 5 s is killed (the script's default waits 40 s)
    r = subprocess.run(["bash", str(ROOT / "cluster" / "stop-head.sh")], env=env | {"RAY_STOP_GRACE": "5"},
                       capture_output=True, text=True, timeout=120)
    shutil.rmtree(head_dir, ignore_errors=True)
    assert "stopped the Ray head" in r.stdout, r.stdout + r.stderr


def pipeline(name, args, env, **kw):
    return subprocess.run([sys.executable, str(ROOT / "pipelines" / name)] + args, env=env, capture_output=True,
                          text=True, timeout=300, **kw)


def test_head_binds_dashboard_to_loopback_and_requires_the_token(head):
    r = subprocess.run(["ray", "job", "list", "--address", head["JOBS"]],
                       env={**head, "RAY_AUTH_TOKEN": "not-the-token"}, capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "authentication" in (r.stdout + r.stderr).lower()
    out = subprocess.run(["ss", "-ltn"], capture_output=True, text=True).stdout
    dash_port = head["JOBS"].rsplit(":", 1)[1]
    listeners = [l.split()[3] for l in out.splitlines()[1:] if l.split()[3].endswith(":" + dash_port)]
    assert listeners and all(a.startswith("127.0.0.1:") for a in listeners), listeners


def test_job_submit_generates_20_maps(head, tmp_path):
    out = tmp_path / "ds"
    t0 = time.time()
    r = subprocess.run(["ray", "job", "submit", "--address", head["JOBS"], "--runtime-env",
                        str(ROOT / "cluster" / "runtime_env.yaml"), "--working-dir", str(ROOT), "--",
                        "python", "pipelines/generate.py", "--maps", "train", "--num-maps", "20",
                        "--episodes-per-map", "2", "--out", str(out)],
                       env=head, capture_output=True, text=True, timeout=300, cwd=ROOT)
    seconds = time.time() - t0 + float(head["START_SECONDS"])
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "succeeded" in r.stdout + r.stderr and "episodes/s" in r.stdout
    maps, eps = read_run(out)
    assert len(maps) == 20
    m = json.loads((out / "manifest.json").read_text())
    assert m["status"] == "complete" and m["throughput"]["workers"] == 2
    # the job ran the uploaded copy of the code (complete, or imports would fail), not this checkout
    assert Path(m["code_version"]["path"]) != ROOT and "runtime_resources" in m["code_version"]["path"]
    print(f"20 maps via ray job submit: {seconds:.1f} s including the head start")
    assert seconds < 120


def test_job_submit_pretrains_with_two_ddp_workers(head, tmp_path, expert_dataset):
    out = tmp_path / "run"
    r = subprocess.run(["ray", "job", "submit", "--address", head["JOBS"], "--runtime-env",
                        str(ROOT / "cluster" / "runtime_env.yaml"), "--working-dir", str(ROOT), "--",
                        "python", "pipelines/pretrain.py", "--data", expert_dataset, "--out", str(out),
                        "--preset", "tiny", "--steps", "2", "--batch-size", "4", "--workers", "2",
                        "--set", "train.loader_workers=0", "--set", "train.val_fraction=0.34",
                        "--set", "train.val_prompts=2", "--set", "train.log_every=1",
                        "--set", "train.closed_loop_every=0"],
                       env=head, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "succeeded" in r.stdout + r.stderr and "2 x 2 worker(s)" in r.stdout + r.stderr
    cfg = json.loads((out / "checkpoint-0000002" / "config.json").read_text())
    assert cfg["world_size"] == 2 and "runtime_resources" in cfg["code_version"]["path"]


def test_one_ray_train_worker_matches_the_in_process_first_step(head, tmp_path, expert_dataset):
    tiny = ["--data", expert_dataset, "--preset", "tiny", "--steps", "1", "--batch-size", "8", "--set",
            "train.loader_workers=0", "--set", "train.log_every=1", "--set", "train.val_fraction=0.34",
            "--set", "train.val_prompts=2", "--set", "train.closed_loop_every=0"]
    local = pipeline("pretrain.py", tiny + ["--out", str(tmp_path / "local"), "--workers", "0"], head)
    assert local.returncode == 0, local.stderr[-2000:]
    remote = pipeline("pretrain.py", tiny + ["--out", str(tmp_path / "ray"), "--address", head["GCS"],
                                             "--workers", "1"], head)
    assert remote.returncode == 0, remote.stderr[-3000:]
    a, b = (json.loads((tmp_path / d / "metrics.jsonl").read_text().splitlines()[0]) for d in ("local", "ray"))
    assert a["losses/total"] == pytest.approx(b["losses/total"], rel=1e-6)
    assert a["losses/traj"] == pytest.approx(b["losses/traj"], rel=1e-6)


def test_wrong_or_missing_token_and_no_cluster_are_named(head, tmp_path):
    args = ["--maps", "train", "--num-maps", "1", "--out", str(tmp_path / "ds")]
    wrong = {k: v for k, v in head.items() if k != "RAY_AUTH_TOKEN_PATH"} | {"RAY_AUTH_TOKEN": "0" * 64}
    r = pipeline("generate.py", args + ["--address", head["GCS"]], wrong)
    assert r.returncode == 2 and "token is not the cluster's" in r.stderr.splitlines()[-1], r.stderr[-2000:]
    none = {k: v for k, v in head.items() if k not in ("RAY_AUTH_TOKEN_PATH", "RAY_AUTH_TOKEN")} | {
        "HOME": str(tmp_path)}
    r = pipeline("generate.py", args + ["--address", head["GCS"]], none)
    assert r.returncode == 2 and "no Ray authentication token" in r.stderr, r.stderr[-2000:]
    r = pipeline("generate.py", args + ["--address", "127.0.0.1:1"], head)
    assert r.returncode == 2 and "no Ray cluster answers at 127.0.0.1:1" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "ds").exists()


def test_worker_killed_mid_run_is_retried(head, tmp_path):
    ref = tmp_path / "ref"
    args = ["--maps", "train", "--num-maps", "10", "--episodes-per-map", "3", "--set", "dataset.maps_per_unit=1",
            "--set", "expert.batch_size=8"]
    r = pipeline("generate.py", args + ["--out", str(ref), "--workers", "0"], head)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "ds"
    log = tmp_path / "stderr.txt"
    with open(log, "w") as err:
        p = subprocess.Popen([sys.executable, str(ROOT / "pipelines" / "generate.py")] + args
                             + ["--out", str(out), "--address", head["GCS"]], env=head, stdout=subprocess.PIPE,
                             stderr=err, text=True)
        t0 = time.time()
        pids = []
        while time.time() - t0 < 120 and not (pids and list((out / "episodes").glob("*.parquet"))):
            pids = re.findall(r"(\d+)@", (m.group(1) if (m := re.search(r"started 2 Ray worker\(s\): (.*)",
                                                                        log.read_text())) else ""))
            time.sleep(0.05)
        assert pids, log.read_text()
        os.kill(int(pids[0]), signal.SIGKILL)  # a worker process dies (OOM killer, lost node...)
        stdout, _ = p.communicate(timeout=300)
    stderr = log.read_text()
    assert p.returncode == 0, stderr
    assert "worker lost" in stderr
    m = json.loads((out / "manifest.json").read_text())
    assert m["retries"] >= 1 and m["failures"] == [] and m["status"] == "complete"
    ids = sorted(e["episode_id"] for e in read_run(out)[1])  # raises on a duplicated id
    assert ids == sorted(e["episode_id"] for e in read_run(ref)[1])  # every unit exactly once
    for f in sorted((ref / "episodes").glob("*.parquet")):
        assert (out / "episodes" / f.name).read_bytes() == f.read_bytes()


def test_evaluation_fans_out_with_identical_episodes(head, tmp_path):
    """The expert, the SGG and GNN baselines and the shipped Roken model on the same tasks, in-process and on 2
    Ray actors: identical episode files (one torch thread in both, as Ray gives each 1-CPU actor)."""
    args = ["--planner", "laplacian,sgg,gnn,roken", "--checkpoint", str(ROOT / "models" / "roken-small-mixed"),
            "--robots", "2,3", "--episodes", "2", "--set", "eval.unit_episodes=1", "--set", "expert.batch_size=4",
            "--steps", "3"]  # 3 DDIM steps: the shipped model fails these tasks and runs to the step limit
    a, b = tmp_path / "inproc", tmp_path / "ray"
    env = {**head, "OMP_NUM_THREADS": "1"}
    r = pipeline("evaluate.py", args + ["--out", str(a), "--workers", "0"], env)
    assert r.returncode == 0, r.stderr
    r = pipeline("evaluate.py", args + ["--out", str(b), "--address", head["GCS"]], env)
    assert r.returncode == 0, r.stderr
    assert "started 2 Ray worker(s)" in r.stderr
    for f in ("n02.parquet", "n03.parquet", "roken-n02.parquet", "roken-n03.parquet", "sgg-n02.parquet",
              "sgg-n03.parquet", "gnn-n02.parquet", "gnn-n03.parquet"):
        assert (a / "episodes" / f).read_bytes() == (b / "episodes" / f).read_bytes(), f
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert ma["planners"] == mb["planners"] and mb["workers"] == 2
    assert set(ma["planners"]) == {"laplacian", "sgg", "gnn", "roken"}
    assert "roken" in r.stdout and "laplacian" in r.stdout


def test_ray_data_reads_the_same_columns(head, tmp_path):
    out = tmp_path / "ds"
    r = pipeline("generate.py", ["--num-maps", "2", "--episodes-per-map", "2", "--out", str(out), "--workers", "0"],
                 head)
    assert r.returncode == 0, r.stderr
    code = f"""
import json, sys
from roken import ray_pool
from roken.data.shards import read_table
ray_pool.connect(address={head['GCS']!r})
ds = ray_pool.read_ray_dataset({str(out)!r})
t = read_table({str(out)!r})
schema = ds.schema()
batch = next(iter(ds.iter_batches(batch_size=100, batch_format="pyarrow")))
print(json.dumps({{"names": list(schema.names), "types": [str(x) for x in schema.types],
    "pa_names": t.column_names, "pa_types": [str(f.type) for f in t.schema], "rows": ds.count(),
    "pa_rows": t.num_rows, "batch_types": [str(f.type) for f in batch.schema]}}))
"""
    r = subprocess.run([sys.executable, "-c", code], env=head, capture_output=True, text=True, timeout=180,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["names"] == got["pa_names"] and got["types"] == got["pa_types"] == got["batch_types"]
    assert got["rows"] == got["pa_rows"] > 0
    assert "list<element: float>" in got["types"] and not any("tensor" in t.lower() for t in got["types"])


def test_ray_data_batches_of_training_samples(head, expert_dataset):
    """Ray Data's map_batches turns episode rows into training samples equal to the in-process ones."""
    code = f"""
import json
import numpy as np
from roken import ray_pool
from roken.data import shards
from roken.data.loader import EpisodeBatchToSamples
from roken.data.samples import SampleConfig
ray_pool.connect(address={head['GCS']!r})
fn = EpisodeBatchToSamples({expert_dataset!r}, SampleConfig(), seed=5)
ds = ray_pool.read_ray_dataset({expert_dataset!r}).map_batches(fn, batch_size=5, batch_format="numpy")
rows = {{}}
for b in ds.iter_torch_batches(batch_size=7):
    for i in range(len(b["chunk"])):
        rows[b["start"][i].numpy().tobytes()] = b["chunk"][i].numpy()
t = shards.read_table({expert_dataset!r}, "episodes")
ref = fn({{c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}})
same = all(np.array_equal(rows[ref["start"][i].tobytes()], ref["chunk"][i])
           for i in range(len(ref["chunk"])))
print(json.dumps({{"n": len(rows), "ref": len(ref["chunk"]), "same": same,
                   "keys": sorted(b.keys()), "dtype": str(b["robot_mask"].dtype)}}))
"""
    r = subprocess.run([sys.executable, "-c", code], env=head, capture_output=True, text=True, timeout=180, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["n"] == got["ref"] > 0 and got["same"], got
    assert "chunk" in got["keys"] and "map" in got["keys"] and got["dtype"] == "torch.bool"


def test_evaluation_on_ray_reports_episodes_as_they_finish(head, tmp_path):
    """Issue 19.13: a Roken unit on a Ray actor reports its finished episodes while it runs (the driver polls
    the actor), not only when the whole unit returns."""
    args = ["--planner", "roken", "--checkpoint", str(ROOT / "models" / "roken-small-mixed"), "--robots", "2",
            "--episodes", "8", "--set", "eval.unit_episodes=8", "--set", "plan.batch_size=1", "--steps", "3",
            "--out", str(tmp_path / "ev"), "--address", head["GCS"], "--workers", "1"]
    r = pipeline("evaluate.py", args, {**head, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    counts = [int(m) for m in re.findall(r"\[roken\] (\d+)/8 ", r.stderr)]
    assert counts[-1] == 8 and any(0 < c < 8 for c in counts), r.stderr[-2000:]
    assert counts == sorted(counts)
