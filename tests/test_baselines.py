"""The paper's SGG and GNN baselines under the evaluation harness: stored episodes pass `roken validate` and the
metric recomputation, SGG keeps every constraint whenever its candidate search found a feasible topology, and
the GNN scorer trains from simulator labels and learns them."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import cli, in_process

from roken.config import load_config
from roken.eval.harness import make_tasks
from roken.expert.sgg import SGGPlanner, team_feasible
from roken.world.maps import generate_map

ROOT = Path(__file__).resolve().parents[1]


def test_sgg_and_gnn_write_valid_episodes_with_the_shared_metrics(tmp_path):
    out = tmp_path / "ev"
    cmd = [sys.executable, str(ROOT / "pipelines" / "evaluate.py"), "--planner", "laplacian,sgg,gnn", "--robots",
           "4", "--episodes", "4", "--maps", "val", "--workers", "0", "--out", str(out)]
    r = in_process(cmd)
    assert r.returncode == 0, r.stderr[-3000:]
    for name in ("sgg-n04.parquet", "gnn-n04.parquet"):
        assert (out / "episodes" / name).is_file()
    v = cli("roken", "validate", str(out))
    assert v.returncode == 0, v.stdout + v.stderr
    from roken.data.store import read_run
    from roken.eval.metrics import episode_metrics, summarize
    from roken.world.tasks import TaskConfig

    metrics = json.loads((out / "metrics.json").read_text())
    maps, eps = read_run(out)
    for p in ("sgg", "gnn"):
        mine = [e for e in eps if e["planner"] == p]
        assert len(mine) == 4
        again = summarize([episode_metrics(e["positions"], maps[e["map_id"]], e["goal"], e["leader"], TaskConfig())
                           for e in mine])
        for k in ("full_success", "reach", "connectivity", "obstacle_collision", "inter_collision"):
            assert again[k] == pytest.approx(metrics["planners"][p][k])
        steps = np.concatenate([np.diff(np.asarray(e["positions"]).reshape(-1, 4, 2), axis=0) for e in mine])
        assert np.linalg.norm(steps, axis=-1).max() <= 0.5 + 1e-5  # never faster than max_step
    r2 = in_process(cmd)  # a re-run reuses every file
    assert r2.returncode == 0 and r2.stderr.count("reusing") == 3


def test_sgg_keeps_the_constraints_whenever_its_search_found_a_feasible_topology():
    cfg = load_config(None, ["eval.episodes=6"])
    maps = [generate_map(cfg.map, "val", i) for i in range(6)]
    tasks, _ = make_tasks(cfg, maps, 4)
    by_id = {m.map_id: m for m in maps}
    seen = 0
    for i, pos, info in SGGPlanner(cfg.sgg, cfg.task, cfg.expert).run([t for _, t in tasks], by_id):
        gm = by_id[tasks[i][1].map_id]
        feas = info["feasible"]
        assert len(feas) == len(pos) - 1
        after = pos[1:][feas].astype(np.float64)  # the positions each feasible decision step chose
        padded = np.broadcast_to(gm.padded, (len(after),) + gm.padded.shape)
        assert team_feasible(after, padded, cfg.task).all()
        seen += int(feas.sum())
    assert seen > 100


def test_gnn_scorer_trains_on_simulator_labels(tmp_path):
    out = tmp_path / "gnn"
    r = cli("roken", "train-gnn", "--out", str(out), "--tasks", "24", "--states", "4", "--steps", "600")
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert 0.05 < s["good_fraction"] < 0.95  # both kinds of candidate graph are in the data
    # and the scorer tells them apart on other maps' graphs, well above always saying "bad" (~0.82 here; with 8
    # tasks it over-fitted: train 1.000, held-out 0.877, below that rate)
    assert s["heldout_accuracy"] > max(0.93, 1 - s["good_fraction"] + 0.05)
    from roken.expert.gnn import load_scorer

    load_scorer(str(out))
    bad = cli("evaluate.py", "--planner", "gnn", "--episodes", "1", "--workers", "0", "--out", str(tmp_path / "ev"),
              "--set", f"gnn.checkpoint={tmp_path / 'none'}")
    assert bad.returncode == 2 and "train-gnn" in bad.stderr and not (tmp_path / "ev").exists()
