"""roken compare: paired sign test of two evaluations on the same tasks."""
import numpy as np
import pytest

from roken.cli import main
from roken.data.store import atomic_write_table, episodes_table
from roken.eval.compare import compare


def _rows(planner, success, shift=0.0):
    rows = []
    for seed, ok in enumerate(success):
        start = np.array([[seed, 1.0], [seed + 1.0, 2.0]], np.float32) + shift
        pos = np.stack([start, start + 0.5])  # (T+1, N, 2)
        rows.append({"episode_id": f"{planner}-n02-e{seed:05d}", "map_id": f"m{seed % 3}", "planner": planner,
                     "leader": 0, "goal": [5.0, 5.0], "positions": pos, "success": bool(ok), "reach": True,
                     "obstacle_collision": False, "inter_collision": False, "connectivity": True,
                     "path_length": 1.0, "astar_length": 1.0, "seed": seed})
    return rows


def _write(folder, planner, success, shift=0.0):
    name = planner.replace("+", "-") + "-n02.parquet"
    atomic_write_table(episodes_table(_rows(planner, success, shift)), folder / "episodes" / name, "episodes")


def test_paired_counts_and_sign_test(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    # 20 tasks: both solve 6, only A solves 1, only B solves 9, neither 4
    sa = [1] * 6 + [1] * 1 + [0] * 9 + [0] * 4
    sb = [1] * 6 + [0] * 1 + [1] * 9 + [0] * 4
    _write(a, "roken+guided", sa)
    _write(b, "roken+guided", sb)
    (r,) = compare(a, b)
    assert (r.tasks, r.only_a, r.only_b) == (20, 1, 9)
    assert r.rate_a == pytest.approx(0.35) and r.rate_b == pytest.approx(0.75)
    # exact two-sided sign test on the 10 discordant tasks: 2 * (C(10,0) + C(10,1)) / 2^10
    assert r.p_value == pytest.approx(22 / 1024)


def test_identical_runs_are_not_different(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    s = [1, 0, 1, 1, 0, 0, 1, 0]
    _write(a, "roken", s)
    _write(b, "roken", s)
    (r,) = compare(a, b)
    assert (r.only_a, r.only_b, r.p_value) == (0, 0, 1.0)


def test_two_planners_of_one_folder(tmp_path, capsys):
    a = tmp_path / "a"
    _write(a, "roken", [0, 0, 0, 1])
    _write(a, "roken+guided+safe", [1, 1, 0, 1])
    (r,) = compare(a, planners=["roken"], against="roken+guided+safe")
    assert (r.planner_a, r.planner_b, r.only_a, r.only_b) == ("roken", "roken+guided+safe", 0, 2)
    assert main(["compare", str(a), "--planner", "roken", "--against", "roken+guided+safe"]) == 0
    out = capsys.readouterr().out
    assert "roken+guided+safe" in out and "+0.500" in out


def test_different_tasks_and_bad_input_are_refused(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, "roken", [1, 0, 1])
    _write(b, "roken", [1, 0, 1], shift=0.25)  # same seeds, other starts: not the same tasks
    with pytest.raises(ValueError, match="not the same task"):
        compare(a, b)
    with pytest.raises(ValueError, match="--planner nope"):
        compare(a, a, planners=["nope"])
    assert main(["compare", str(a)]) == 2
    assert "--against" in capsys.readouterr().err
    assert main(["compare", str(tmp_path / "missing"), str(a)]) == 2
    assert "no episodes" in capsys.readouterr().err
