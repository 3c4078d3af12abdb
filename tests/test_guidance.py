"""Constraint-guided sampling: the spanning trees are minimal, the descent lowers the cost without moving given
robots, and the roken+guided rows run under the harness."""
from pathlib import Path

import numpy as np
import torch
from conftest import cli
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
        i, j = mst_edges(d, real)
        for m in range(20):
            k = real[m].sum()
            ours = d[m][i[m], j[m]].sum()
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


def test_closed_form_gradient_matches_autograd_of_the_cost():
    """The descent's closed-form gradient (Guide.grad) equals autograd through the reference cost, with every
    term on, a padded robot, a leader-less prompt and points outside the map."""
    cfg = load_config(None, ["plan.guide=true", "plan.guide_goal=0.7", "plan.guide_connect=1.3",
                             "plan.guide_follow=0.9", "plan.guide_follow_range=8"])
    rng = np.random.default_rng(1)
    occ = (rng.random((140, 140)) < 0.05).astype(np.uint8)
    sdf, geo = known_fields(occ, (100.0, 70.0))
    B, R = 3, 4
    start = rng.uniform(40, 100, (B, R, 2)).astype(np.float32)
    real = np.ones((B, R), bool)
    real[1, 3] = False
    leader = np.array([0, 2, -1])
    lead = np.stack([known_fields(occ, start[b, max(leader[b], 0)])[1] for b in range(B)])  # the follow term
    out_pts = rng.uniform(30, 110, (B, 3, 16, 2)).astype(np.float32)  # robots outside the prompt (clusters)
    out_w = (rng.random((B, 3, 16)) < 0.7).astype(np.float32)
    guide = Guide(cfg.plan, cfg.task, cfg.samples, start, real, real, leader, np.stack([sdf] * B),
                  np.stack([geo] * B), G=2, lead=lead, outside=(out_pts, out_w))
    assert guide.lead is not None and guide.out_pts is not None
    p = torch.as_tensor(rng.uniform(30, 110, (B * 2, R, 16, 2)), dtype=torch.float32)
    p[0, 0, 0] = torch.tensor([-3.0, 150.0])  # outside the canvas: the border value, no gradient
    p[0, 0, 1] = torch.tensor([139.9999, 139.99999])  # the last cell's far edge, in float32
    p[2, 1, :] = p[2, 2, :] + 0.5  # two robots too close: the inter-robot term
    p[4, 0, :] = p[4, 1, :] + 30.0  # far apart: the connectivity term
    p[5, 1, :] = torch.as_tensor(out_pts[2, 0]) + 0.4  # close to a robot outside the prompt
    q = p.clone().requires_grad_(True)
    (ref,) = torch.autograd.grad(guide.cost(q).sum(), q)
    ours = torch.from_numpy(guide.grad(p.numpy()))
    assert ref.abs().max() > 0.1
    assert torch.allclose(ours, ref, atol=1e-4, rtol=1e-3), (ours - ref).abs().max()


def test_guided_rows_run_under_the_harness(tmp_path):
    r = cli("evaluate.py", "--planner", "roken+guided", "--checkpoint", str(ROOT / "models" / "roken-small-mixed"),
            "--robots", "3", "--episodes", "2", "--num-maps", "2", "--steps", "3", "--guide-steps", "2",
            "--set", "plan.guide_iters=5", "--workers", "0", "--out", str(tmp_path / "ev"))
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "ev" / "episodes" / "roken-guided-n03.parquet").is_file()
    assert "roken+guided" in r.stdout


def test_guidance_leaves_a_clean_chunk_unchanged():
    """A clean chunk within full speed comes back unchanged at --guide-scale 0, and also at scale 1 when every
    constraint term is satisfied (no goal pull), at every guided step's iteration count."""
    from dataclasses import replace

    from roken.model.losses import decode_chunk

    cfg = load_config(None, ["plan.guide=true"])
    occ = np.zeros((140, 140), np.uint8)
    occ[60:80, 70:72] = 1
    sdf, geo = known_fields(occ, (100.0, 70.0))
    start = np.array([[[40.0, 70.0], [36.0, 66.0], [36.0, 74.0]]], np.float32)  # 5.7 m apart, far from the wall
    real = np.ones((1, 3), bool)
    rng = np.random.default_rng(0)
    G = 4
    ang = rng.uniform(-0.3, 0.3, (G, 1, 16, 1))
    x0 = torch.as_tensor(np.concatenate([np.cos(ang), np.sin(ang)], -1) * 0.4, dtype=torch.float32)  # 0.8 m moves
    x0 = x0.expand(G, 3, 16, 2).contiguous()  # the team moves together, at 0.4 of full speed
    given, fixed = torch.zeros_like(x0), torch.zeros(G, 3, 1, 1, dtype=torch.bool)
    for pc in (replace(cfg.plan, guide_scale=0.0), replace(cfg.plan, guide_goal=0.0),
               replace(cfg.plan, guide_scale=0.0, guide_final_iters=0, guide_iters=7)):
        guide = Guide(pc, cfg.task, cfg.samples, start, real, real, np.array([0]), sdf[None], geo[None], G)
        assert float(guide.cost(decode_chunk(x0, guide.start, cfg.samples)).max()) == 0.0 or pc.guide_scale == 0
        for last in (False, True):
            out = guide(x0, given, fixed, last=last)
            assert torch.allclose(out, x0, atol=1e-5), (out - x0).abs().max()


def test_guidance_keeps_clear_of_robots_outside_the_prompt():
    """A robot outside the cluster (clustered rollout) standing on the generated robot's path pushes the path
    aside over the weighted moves; without it the path goes straight through."""
    from roken.model.losses import decode_chunk

    cfg = load_config(None, ["plan.guide=true", "plan.guide_goal=0"])
    occ = np.zeros((140, 140), np.uint8)
    sdf, geo = known_fields(occ, (100.0, 70.0))
    start = np.array([[[40.0, 70.0]]], np.float32)
    x0 = torch.zeros(1, 1, 16, 2)
    x0[..., 0] = 0.4  # 0.8 m per move along +x
    given, fixed = torch.zeros_like(x0), torch.zeros(1, 1, 1, 1, dtype=torch.bool)
    stand = np.broadcast_to(np.array([41.6, 70.5], np.float32), (1, 1, 16, 2)).copy()  # beside move 2's point
    w = np.zeros((1, 1, 16), np.float32)
    w[0, 0, :2] = 1  # the executed moves only
    base = Guide(cfg.plan, cfg.task, cfg.samples, start, np.ones((1, 1), bool), np.ones((1, 1), bool),
                 np.array([0]), sdf[None], geo[None], 1)
    assert torch.allclose(base(x0, given, fixed), x0, atol=1e-5)
    guide = Guide(cfg.plan, cfg.task, cfg.samples, start, np.ones((1, 1), bool), np.ones((1, 1), bool),
                  np.array([0]), sdf[None], geo[None], 1, outside=(stand, w))
    out = decode_chunk(guide(x0, given, fixed), guide.start, cfg.samples)[0, 0].numpy()
    d = np.linalg.norm(out[:2] - stand[0, 0, :2], axis=-1)
    assert d.min() >= cfg.task.d_coll_min, d
