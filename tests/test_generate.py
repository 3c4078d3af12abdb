"""Dataset generation: in-process and on a local Ray cluster, resume after a kill, manifest, read path."""
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from conftest import cli

from roken.config import load_config
from roken.data import fs
from roken.data.build import build_dataset
from roken.data.shards import read_table
from roken.data.store import read_run
from roken.units import InProcessRunner

ROOT = Path(__file__).resolve().parents[1]
GENERATE = [sys.executable, str(ROOT / "pipelines" / "generate.py")]
# 8 units of one map x 3 episodes: small, but enough units to kill a run between them.
SMALL = ["--maps", "train", "--num-maps", "8", "--episodes-per-map", "3", "--set", "dataset.maps_per_unit=1",
         "--set", "expert.batch_size=8", "--set", "dataset.keep_failed=true"]
EXPECTED_IDS = {f"train-{i:06d}-e{k:02d}" for i in range(8) for k in range(3)}


def run(args, env=None, timeout=300, **kw):
    if "--local" not in args and env is None and not kw:  # in-process runs need no interpreter of their own
        return cli("generate.py", *args)
    return subprocess.run(GENERATE + args, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})}, **kw)


def shard_bytes(out: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted((out / "episodes").glob("*.parquet"))}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The small dataset made in-process: every other run of the same command must equal it byte for byte."""
    out = tmp_path_factory.mktemp("ref") / "ds"
    r = run(SMALL + ["--out", str(out), "--workers", "0"])
    assert r.returncode == 0, r.stderr
    return out


def test_in_process_dataset_contract(reference):
    maps, eps = read_run(reference)  # the store's validator: schema, sizes, maps present, unique ids
    assert {e["episode_id"] for e in eps} == EXPECTED_IDS
    assert len(maps) == 8 and len(list((reference / "episodes").glob("*.parquet"))) == 8
    m = json.loads((reference / "manifest.json").read_text())
    assert m["status"] == "complete" and m["units_total"] == 8 and m["episodes"] == 24
    assert [s["unit"] for s in m["shards"]] == [f"unit-{u:05d}" for u in range(8)]
    assert sum(s["rows"] for s in m["shards"]) == 24 and m["failures"] == []
    assert m["config"]["dataset"]["episodes_per_map"] == 3 and m["code_version"]["python"]
    assert sum(v["attempted"] for v in m["by_team_size"].values()) == 24
    assert set(m["by_team_size"]) <= {str(n) for n in range(2, 9)}
    for s in m["shards"]:  # row counts in the manifest are the files' row counts
        assert pq.read_metadata(reference / s["episodes"]).num_rows == s["rows"]
    r = cli("roken", "validate", str(reference))
    assert r.returncode == 0 and "manifest complete, 8 shards" in r.stdout, r.stdout + r.stderr


def test_rerun_skips_finished_shards_and_refuses_another_config(reference, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(reference, out)
    (out / "episodes" / "unit-00003.parquet").unlink()  # as if the run had stopped before this unit
    before = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").glob("*.parquet")}
    r = run(SMALL + ["--out", str(out), "--workers", "0"])
    assert r.returncode == 0, r.stderr
    assert "7 finished earlier, 1 to run" in r.stderr
    after = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").glob("*.parquet")}
    assert all(after[k] == v for k, v in before.items())  # finished shards untouched
    assert shard_bytes(out) == shard_bytes(reference)
    r = run(SMALL + ["--out", str(out), "--workers", "0", "--episodes-per-map", "4"])
    assert r.returncode == 2 and "dataset.episodes_per_map: 3 -> 4" in r.stderr
    assert shard_bytes(out) == shard_bytes(reference)  # nothing already written is lost


@pytest.mark.slow
def test_local_ray_cluster_gives_the_same_dataset(reference, tmp_path, ray_tmp):
    out = tmp_path / "ds"
    r = run(SMALL + ["--out", str(out), "--local", "--num-cpus", "2"], env={"RAY_TMPDIR": ray_tmp})
    assert r.returncode == 0, r.stderr
    assert "started 2 Ray worker(s)" in r.stderr and "episodes/s" in r.stdout
    assert shard_bytes(out) == shard_bytes(reference)
    read_run(out)


@pytest.mark.slow
def test_killed_run_resumes_without_loss_or_duplicates(reference, tmp_path, ray_tmp):
    out = tmp_path / "ds"
    env = {"RAY_TMPDIR": ray_tmp}
    p = subprocess.Popen(GENERATE + SMALL + ["--out", str(out), "--local", "--num-cpus", "2"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                         env={**os.environ, **env})
    t0 = time.time()
    while time.time() - t0 < 240 and len(list((out / "episodes").glob("*.parquet"))) < 2:
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)  # the driver and its local cluster, mid-run
    p.wait()
    done_at_kill = len(list((out / "episodes").glob("*.parquet")))
    assert 2 <= done_at_kill < 8, "the run should have been killed midway"
    r = run(SMALL + ["--out", str(out), "--local", "--num-cpus", "2"], env=env)
    assert r.returncode == 0, r.stderr
    # workers already busy may still finish their unit after the driver died: at least the shards seen
    # at the kill are reused, and some units are left to run
    reused = int(re.search(r"(\d+) finished earlier", r.stderr).group(1))
    assert done_at_kill <= reused < 8
    _, eps = read_run(out)  # raises on duplicated ids
    assert sorted(e["episode_id"] for e in eps) == sorted(EXPECTED_IDS)
    assert shard_bytes(out) == shard_bytes(reference)
    assert not list(out.rglob("*.tmp"))  # the killed writer's temporaries were cleaned up


def test_external_maps_with_a_corrupt_file(tmp_path):
    import numpy as np

    maps = tmp_path / "maps"
    maps.mkdir()
    for i in range(2):
        occ = np.zeros((70, 70), np.uint8)
        occ[20 + 10 * i:30 + 10 * i, 30:40] = 1
        np.save(maps / f"room{i}.npy", occ)
    (maps / "broken.map").write_text("type octile\nheight 3\n")
    (maps / "garbage.png").write_bytes(b"not a png")
    out = tmp_path / "ds"
    r = run(["--maps", str(maps), "--episodes-per-map", "2", "--out", str(out), "--workers", "0",
             "--set", "dataset.keep_failed=true"])
    assert r.returncode == 0, r.stderr
    m = json.loads((out / "manifest.json").read_text())
    assert sorted(Path(b["file"]).name for b in m["bad_maps"]) == ["broken.map", "garbage.png"]
    assert all(b["reason"] for b in m["bad_maps"])
    maps_read, eps = read_run(out)
    assert set(maps_read) == {"room0", "room1"} and len(eps) == 4


def test_read_path_pyarrow_pandas_and_uri(reference):
    table = read_table(str(reference))
    assert table.num_rows == 24
    for f in table.schema:  # plain Arrow types only: no extension types inside the files
        assert not isinstance(f.type, __import__("pyarrow").ExtensionType)
    df = table.to_pandas()
    assert list(df.columns) == table.column_names and len(df) == 24
    uri = "file://" + str(reference)
    assert read_table(uri, "maps").num_rows == 8
    maps, eps = read_run(uri)
    assert len(eps) == 24


def test_uri_writes_are_atomic_and_joined_correctly(tmp_path, monkeypatch):
    assert fs.join("s3://bucket/prefix", "episodes", "a.parquet") == "s3://bucket/prefix/episodes/a.parquet"
    assert fs.join("s3://b/p/?region=x", "m.json") == "s3://b/p/m.json?region=x"
    target = "file://" + str(tmp_path / "sub" / "x.bin")
    fs.write_atomic(target, b"abc")
    assert (tmp_path / "sub" / "x.bin").read_bytes() == b"abc"

    real_write = Path.write_bytes

    def half_then_fail(self, data):  # the disk fills up half way through the file
        real_write(self, data[: len(data) // 2])
        raise OSError("No space left on device")

    monkeypatch.setattr(Path, "write_bytes", half_then_fail)
    with pytest.raises(OSError, match="No space"):
        fs.write_atomic(tmp_path / "sub" / "y.bin", b"0123456789")
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["x.bin"]  # no partial file, no temp


def test_build_dataset_api_reports_a_failing_unit(tmp_path, monkeypatch):
    """A unit whose code raises is listed in the manifest; the other units are kept; a re-run finishes."""
    cfg = load_config(None, ["dataset.num_maps=3", "dataset.episodes_per_map=1", "dataset.maps_per_unit=1",
                             "expert.batch_size=4"])
    import roken.data.generation as gen

    real = gen.generate_unit

    def flaky(ctx, payload, cache):
        if payload["key"] == "unit-00001":
            raise RuntimeError("simulated bug")
        return real(ctx, payload, cache)

    monkeypatch.setattr(gen, "generate_unit", flaky)
    m = build_dataset(cfg, str(tmp_path), InProcessRunner())
    assert m["status"] == "incomplete" and [f["unit"] for f in m["failures"]] == ["unit-00001"]
    assert "simulated bug" in m["failures"][0]["error"] and len(m["shards"]) == 2
    monkeypatch.setattr(gen, "generate_unit", real)
    m = build_dataset(cfg, str(tmp_path), InProcessRunner())
    assert m["status"] == "complete" and len(m["shards"]) == 3


def test_bad_team_sizes_are_rejected(tmp_path):
    r = run(["--out", str(tmp_path / "o"), "--workers", "0", "--set", "dataset.team_sizes={4: 0}"])
    assert r.returncode == 2 and "dataset.team_sizes" in r.stderr
    assert not (tmp_path / "o").exists()  # refused before anything was written


def test_disturb_makes_dart_episodes(tmp_path):
    """expert.disturb (DART): each episode is the expert's own run up to its push, pushed off course for
    disturb_steps, then the expert's recovery with its hidden state intact; training chunks start right after the
    push; the episodes stay feasible, and the push is drawn from the task's seed (the same every run)."""
    import numpy as np

    from roken.data.samples import EpisodeBank

    args = ["--maps", "train", "--num-maps", "2", "--episodes-per-map", "3", "--set", "dataset.team_sizes={4: 1}",
            "--workers", "0"]
    assert run(args + ["--out", str(tmp_path / "plain")]).returncode == 0
    push = args + ["--set", "expert.disturb=0.15", "--set", "dataset.disturb_window=12"]
    r = run(push + ["--out", str(tmp_path / "dart")])
    assert r.returncode == 0, r.stderr
    _, plain = read_run(tmp_path / "plain")
    _, dart = read_run(tmp_path / "dart")
    plain = {e["episode_id"]: e for e in plain}
    assert dart and all(e["source"] == "dart" and e["success"] for e in dart)
    moved = []
    for e in dart:
        at = e["sample_from"] - 8  # expert.disturb_steps
        assert e["sample_until"] == e["sample_from"] + 12 and 0 <= at
        P = np.asarray(e["positions"]).reshape(-1, 4, 2)
        Q = np.asarray(plain[e["episode_id"]]["positions"]).reshape(-1, 4, 2)
        assert np.allclose(P[:max(at - 2, 0)], Q[:max(at - 2, 0)], atol=1e-5)  # the same run up to the push
        if at + 8 < min(len(P), len(Q)):
            moved.append(np.linalg.norm(P[at + 8] - Q[at + 8], axis=-1).mean())
    assert moved and np.median(moved) > 0.4  # pushed off course (0.88 m at 0.15 m/step on 40 val tasks)
    r = cli("roken", "validate", str(tmp_path / "dart"))
    assert r.returncode == 0, r.stdout + r.stderr
    bank = EpisodeBank.from_arrow(read_table(str(tmp_path / "dart"), "episodes"),
                                  read_table(str(tmp_path / "dart"), "maps"))
    by_id = {e["episode_id"]: e for e in dart}  # the window is what training reads (make_sample draws in it)
    assert [int(bank.sample_from[i]) for i in range(len(bank.episode_ids))] == \
        [by_id[k]["sample_from"] for k in bank.episode_ids]
    assert [int(bank.sample_until[i]) for i in range(len(bank.episode_ids))] == \
        [by_id[k]["sample_until"] for k in bank.episode_ids]
    folder = EpisodeBank.from_folder(str(tmp_path / "dart"))
    assert (folder.sample_from == bank.sample_from).all() and (folder.sample_until == bank.sample_until).all()
    assert run(push + ["--out", str(tmp_path / "again")]).returncode == 0
    assert shard_bytes(tmp_path / "again") == shard_bytes(tmp_path / "dart")  # the push is the task seed's
    for bad, why in ((["--set", "expert.disturb=-0.1"], "expert.disturb"),
                     (["--set", "expert.disturb=0.1", "--set", "dataset.restart_every=40"], "restart_every")):
        r = run(args + bad + ["--out", str(tmp_path / "bad")])
        assert r.returncode == 2 and why in r.stderr and not (tmp_path / "bad").exists()


def test_restart_every_keeps_markov_labels(tmp_path):
    """dataset.restart_every: the expert restarted from every k-th step of each kept episode, each continuation
    the expert's own run from that state, and every training chunk starting at an episode's first step."""
    import numpy as np

    from roken.data.build import fingerprint
    from roken.data.samples import EpisodeBank
    from roken.expert.laplacian import LaplacianExpert
    from roken.world.tasks import Task

    out = tmp_path / "ds"
    args = ["--maps", "train", "--num-maps", "2", "--episodes-per-map", "2", "--set", "dataset.team_sizes={3: 1}"]
    r = run(args + ["--set", "dataset.restart_every=40", "--out", str(out), "--workers", "0"])
    assert r.returncode == 0, r.stderr
    maps, eps = read_run(out)
    recorded = {e["episode_id"]: e for e in eps if re.fullmatch(r"train-\d{6}-e\d\d", e["episode_id"])}
    restarts = {e["episode_id"]: e for e in eps if e["episode_id"] not in recorded}
    assert len(recorded) == 4 and restarts and all(e["sample_until"] == 1 for e in eps)
    tc = load_config(None, []).task
    for eid, e in recorded.items():  # a restart at every 40th step before the leader comes within eps_goal
        P = np.asarray(e["positions"]).reshape(-1, e["num_robots"], 2)
        near = np.flatnonzero(np.linalg.norm(P[:, e["leader"]] - e["goal"], axis=-1) <= tc.eps_goal)
        want = {f"{eid}-r{t:04d}" for t in range(40, int(near[0]), 40)}
        assert {k for k in restarts if k.startswith(eid + "-")} == want
    eid, e = sorted(restarts.items())[0]
    base = recorded[eid.rsplit("-", 1)[0]]
    t = int(eid.rsplit("-r", 1)[1])
    P = np.asarray(base["positions"]).reshape(-1, base["num_robots"], 2)
    Q = np.asarray(e["positions"]).reshape(-1, e["num_robots"], 2)
    assert np.allclose(Q[0], P[t], atol=1e-5) and e["leader"] == base["leader"]
    cfg = load_config(None, [])
    (_, again), = LaplacianExpert(cfg.expert, cfg.task).run([Task(e["map_id"], P[t].astype(np.float64),
                                                                 np.asarray(e["goal"], np.float64), e["leader"])], maps)
    assert np.allclose(again.positions[:65], Q[:65], atol=1e-3)  # the expert's answer to the positions alone
    r = cli("roken", "validate", str(out))
    assert r.returncode == 0, r.stdout + r.stderr
    episodes = read_table(str(out), "episodes")
    bank = EpisodeBank.from_arrow(episodes, read_table(str(out), "maps"))
    assert bank.sample_until is not None and (bank.sample_until == 1).all()
    folder = EpisodeBank.from_folder(str(out))  # what the benchmarks and GRPO's prompts read: the same windows
    assert folder.sample_until is not None and (folder.sample_until == 1).all()
    # the field's default leaves the fingerprint of datasets made before it (e.g. the model cards' train4)
    old = load_config(None, ["dataset.num_maps=1500", "dataset.episodes_per_map=10", "dataset.team_sizes={4: 1}"])
    assert fingerprint(old) == "d087d934ef9745d5"
