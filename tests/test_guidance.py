"""Constraint-guided sampling: the spanning trees are minimal, the descent lowers the cost without moving given
robots, and the roken+guided rows run under the harness."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.sparse.csgraph import minimum_spanning_tree

from roken.config import load_config
from roken.plan.guidance import Guide, known_fields, mst_edges

ROOT = Path(__file__).resolve().parents[1]


def test_mst_edges_are_minimum_spanning_trees():
    rng = np.random.default_rng(0)
    for n in (2, 3, 4, 7):
        pts = rng.uniform(0, 30, (20, n, 2))
        d = np.linalg.norm(pts[:, :, None] - pts[:, None], axis=-1)
        real = np.ones((20, n), bool)
        real[::3, -1] = False  # some graphs with a padded node
        i, j = mst_edges(torch.tensor(d), torch.tensor(real))
        for m in range(20):
            k = real[m].sum()
            ours = d[m][i[m].numpy(), j[m].numpy()].sum()
            ref = minimum_spanning_tree(d[m][:k, :k] + 1e-12).sum()
            assert abs(ours - ref) < 1e-6


def test_guidance_lowers_the_cost_and_never_moves_given_robots():
    cfg = load_config(None, ["plan.guide=true"])
    occ = np.zeros((140, 140), np.uint8)
    occ[60:80, 70:72] = 1  # a wall at x = 70..72
    sdf, geo = known_fields(occ, (100.0, 70.0))
    start = np.zeros((1, 3, 2), np.float32)
    start[0] = [[68.6, 70.0], [60.0, 70.0], [61.0, 70.0]]  # robot 0 close to the wall, robots 1 and 2 1 m apart
    real = np.ones((1, 3), bool)
    gen = np.array([[True, True, False]])  # robot 2 is given (conditional mode)
    guide = Guide(cfg.plan, cfg.task, cfg.samples, start, real, gen, np.array([0]), sdf[None], geo[None], G=2)
    x0 = torch.zeros(2, 3, 16, 2)  # everyone stands still
    given = torch.zeros_like(x0)
    fixed = torch.tensor([False, False, True]).view(1, 3, 1, 1).expand(2, 3, 1, 1)
    from roken.model.losses import decode_chunk
    before = guide.cost(decode_chunk(x0, guide.start, cfg.samples))
    out = guide(x0, given, fixed)
    after = guide.cost(decode_chunk(out, guide.start, cfg.samples))
    assert (after < before).all()
    assert torch.equal(out[:, 2], given[:, 2])  # the given robot is exactly as given
    moves = out.norm(dim=-1)
    assert (moves <= 1.0 + 1e-5).all()  # never faster than full speed


def test_guided_rows_run_under_the_harness(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "pipelines" / "evaluate.py"), "--planner", "roken+guided",
                        "--checkpoint", str(ROOT / "models" / "roken-small-mixed"), "--robots", "3", "--episodes", "2",
                        "--num-maps", "2", "--steps", "3", "--guide-steps", "2", "--set", "plan.guide_iters=5",
                        "--workers", "0", "--out", str(tmp_path / "ev")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "ev" / "episodes" / "roken-guided-n03.parquet").is_file()
    assert "roken+guided" in r.stdout
