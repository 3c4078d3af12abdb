"""The sweeps: every setting evaluates each asked Roken row on the same tasks, and the tables name them."""
import json
import sys
from pathlib import Path

import pytest
from conftest import in_process

from roken.eval.sweeps import line_name, markdown, settings

ROOT = Path(__file__).resolve().parents[1]


def test_settings_carry_every_roken_row_and_refuse_others():
    rows = ("roken", "roken+guided+geodesic")
    sc = settings("scalability", 10, rows)
    assert [s[2]["eval.planner"] for s in sc if s[0] == "direct N=4"] == ["laplacian,sgg,gnn,roken,roken+guided+geodesic"]
    assert all(s[2]["eval.planner"] == "roken,roken+guided+geodesic" for s in sc if s[0].startswith("clustered"))
    assert [s[1] for s in settings("replanning", 10, rows)] == [1, 2, 4, 8]
    assert line_name("scalability", "clustered N=6", "roken") == "clustered"
    assert line_name("scalability", "clustered N=6", "roken+guided") == "roken+guided clustered"
    assert line_name("sensing", "sensing 10 m", "roken+guided") == "roken+guided"
    row = {"setting": "sensing 5 m", "planner": "roken", "episodes": 3, "full_success": 0.0, "obstacle_collision": 1.0,
           "inter_collision": 0.0, "connectivity": 1.0, "reach": 0.0}
    for missing in (float("nan"), None):  # NaN in memory, null once a reused setting's metrics.json is read
        assert markdown("sensing", [row | {"length": missing}]).rstrip().endswith("| 0.000 | - |")
    with pytest.raises(ValueError, match="Roken rows only"):
        settings("sensing", 10, ("roken", "sgg"))


def test_a_sweep_runs_two_rows_on_the_same_tasks_and_resumes(tmp_path):
    cmd = [sys.executable, str(ROOT / "pipelines" / "sweep.py"), "--checkpoint", str(ROOT / "models" / "roken-cpu-four"),
           "--sweeps", "sensing", "--planners", "roken,roken+guided+safe", "--candidates", "2", "--episodes", "1",
           "--set", "eval.num_maps=1", "--set", "plan.steps=2", "--set", "plan.guide_iters=1",
           "--set", "plan.guide_final_iters=2", "--set", "expert.step_limit_factor=0.2", "--workers", "0",
           "--out", str(tmp_path / "sw")]
    r = in_process(cmd)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = json.loads((tmp_path / "sw" / "sensing.json").read_text())["rows"]
    assert sorted({(x["setting"], x["planner"]) for x in rows}) == sorted(
        (s, p) for s in ("whole map", "sensing 20 m", "sensing 10 m", "sensing 5 m") for p in ("roken", "roken+guided+safe"))
    assert (tmp_path / "sw" / "sensing.png").is_file() and "roken+guided+safe" in r.stdout
    again = in_process(cmd)
    assert again.returncode == 0 and again.stdout == r.stdout, "a finished sweep re-runs as a no-op"
