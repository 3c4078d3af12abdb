"""What a new user ran into (issue 12): bad flags fail before anything is written, with the flag and the range;
an evaluation folder of another config is not overwritten; metrics.json is strict JSON; clear file errors."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from roken.data.store import atomic_write_json
from roken.world.loaders import MapError, read_npy

ROOT = Path(__file__).resolve().parents[1]


def run(script, *args):
    return subprocess.run([sys.executable, str(ROOT / "pipelines" / script), *args], capture_output=True, text=True,
                          timeout=300)


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
    r = subprocess.run([sys.executable, "-m", "roken", "validate", str(tmp_path / "ev")], capture_output=True,
                       text=True, timeout=120)
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
