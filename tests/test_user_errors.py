"""What a new user ran into (issue 12): bad flags fail before anything is written, with the flag and the range;
an evaluation folder of another config is not overwritten; metrics.json is strict JSON; clear file errors."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import cli

from roken.data.store import atomic_write_json
from roken.world.loaders import MapError, read_npy

ROOT = Path(__file__).resolve().parents[1]


def run(script, *args):
    return cli(script, *args)


@pytest.mark.parametrize("script,args,message", [
    ("evaluate.py", ["--robots", "0"], "--robots 0: team sizes must be >= 1"),
    ("evaluate.py", ["--robots", "-3"], "--robots -3: team sizes must be >= 1"),
    ("evaluate.py", ["--episodes", "0"], "--episodes 0: must be >= 1"),
    ("evaluate.py", ["--episodes", "-5"], "--episodes -5: must be >= 1"),
    ("generate.py", ["--num-maps", "0"], "--num-maps 0: must be >= 1; omit it"),
    ("generate.py", ["--seed", "-1"], "--seed -1: must be >= 0"),
    ("generate.py", ["--workers", "-1"], "--workers -1: must be >= 0"),
    ("generate.py", ["--local", "--num-cpus", "0"], "--num-cpus 0: must be >= 1"),
])
def test_bad_flags_name_the_flag_and_write_nothing(tmp_path, script, args, message):
    r = run(script, *args, "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def test_evaluation_of_another_config_is_refused_and_metrics_are_strict_json(tmp_path):
    base = ["--robots", "2", "--episodes", "2", "--num-maps", "2", "--workers", "0", "--out", str(tmp_path / "ev")]
    assert run("evaluate.py", *base).returncode == 0
    before = (tmp_path / "ev" / "metrics.json").read_text()
    r = run("evaluate.py", *base[:2], "--episodes", "3", *base[4:])
    assert r.returncode == 2 and "eval.episodes: 2 -> 3" in r.stderr and "--overwrite" in r.stderr
    assert (tmp_path / "ev" / "metrics.json").read_text() == before
    assert run("evaluate.py", *base[:2], "--episodes", "3", *base[4:], "--overwrite").returncode == 0
    assert json.loads((tmp_path / "ev" / "metrics.json").read_text())["episodes"] == 3
    r = cli("roken", "validate", str(tmp_path / "ev"))
    assert r.returncode == 0 and "evaluation folder" in r.stdout


def test_nan_is_written_as_null(tmp_path):
    atomic_write_json({"length": float("nan"), "rows": [np.float64("inf"), 1.5]}, tmp_path / "m.json")
    text = (tmp_path / "m.json").read_text()
    assert "NaN" not in text and json.loads(text) == {"length": None, "rows": [None, 1.5]}


def test_text_renamed_npy_is_not_an_array(tmp_path):
    f = tmp_path / "map.npy"
    f.write_text("just some text\n")
    with pytest.raises(MapError, match="not a valid .npy array file") as e:
        read_npy(f)
    assert "allow_pickle" not in str(e.value)


def test_plot_checks_its_flags_and_says_why_an_episode_failed(expert_dataset, tmp_path):
    from roken.world.grid import GridMap
    from roken.world.metrics import failure_reason
    from roken.world.tasks import TaskConfig

    def plot(*args):
        return cli("roken", "plot", expert_dataset, *args)
    for args, msg in [(["--index", "99999"], "--index 99999"), (["--index", "-1"], "--index -1"),
                      (["--instants", "99999"], "--instants 99999"), (["--instants", "0"], "--instants 0")]:
        r = plot(*args, "--out", str(tmp_path / "p.png"))
        assert r.returncode == 2 and msg in r.stderr and not (tmp_path / "p.png").exists(), r.stderr
    r = plot("--out", str(tmp_path / "no" / "dir" / "p.png"))
    assert r.returncode == 2 and "does not exist" in r.stderr and not (tmp_path / "no").exists()
    assert plot("--out", str(tmp_path / "p.png")).returncode == 0 and (tmp_path / "p.png").stat().st_size > 0

    occ = np.zeros((40, 40), np.uint8)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = 1
    gm, cfg = GridMap("m", occ), TaskConfig()
    walk = np.stack([np.stack([[5.0 + 0.5 * t, 10.0], [5.0 + 0.5 * t, 14.0]]) for t in range(20)])
    assert failure_reason(walk, gm, np.array([30.0, 10.0]), 0, cfg).startswith("time-out after 19 steps")
    assert failure_reason(walk, gm, np.array([14.5, 10.0]), 0, cfg) is None
    crash = walk.copy()
    crash[7:, 1] = [crash[7, 0, 0] + 1.0, 10.0]
    assert failure_reason(crash, gm, np.array([30.0, 10.0]), 0, cfg) == "inter-robot collision at step 7 (robots 0, 1)"
    wall = walk.copy()
    wall[5:, 1, 1] = 1.5
    assert failure_reason(wall, gm, np.array([30.0, 10.0]), 0, cfg) == "obstacle collision at step 5 (robot 1)"
    far = walk.copy()
    far[9:, 1, 1] = 30.0
    assert failure_reason(far, gm, np.array([30.0, 10.0]), 0, cfg) == "disconnected at step 9"


def test_ctrl_c_during_generate_records_the_state_and_resumes(tmp_path):
    import signal
    import time

    out = tmp_path / "ds"
    cmd = [sys.executable, str(ROOT / "pipelines" / "generate.py"), "--maps", "train", "--num-maps", "16",
           "--episodes-per-map", "1", "--workers", "0", "--set", "dataset.maps_per_unit=1",
           "--set", "dataset.team_sizes={2: 1}", "--out", str(out)]
    # 16 one-map units run one after another in-process, so the SIGINT sent when the first file appears lands
    # long before the last unit is done, even on a loaded machine
    # default SIGINT disposition for the child: a background CI job inherits it ignored (no KeyboardInterrupt)
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while not list((out / "episodes").glob("unit-*.parquet")) and time.time() < deadline:
        time.sleep(0.1)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130 and "Traceback" not in err, err
    assert "units written" in err and "re-run the same command to resume" in err
    m = json.loads((out / "manifest.json").read_text())
    assert m["status"] == "interrupted" and m["shards"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and json.loads((out / "manifest.json").read_text())["status"] == "complete"
