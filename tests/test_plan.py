"""The Roken planner: conditional mode, clustered rollout, partial observation, the closed loop, selection."""
from pathlib import Path

import numpy as np
import pytest
from conftest import cli
import torch

from roken.config import load_config
from roken.data.condition import build_condition, sensed_cells
from roken.data.samples import SampleConfig
from roken.eval.harness import make_tasks
from roken.plan import PlanConfig, RokenPlanner, RokenRollout
from roken.plan.clusters import overlapping_clusters
from roken.plan.select import choose, violations
from roken.world.geometry import pad_for_clearance
from roken.world.maps import generate_map

ROOT = Path(__file__).resolve().parents[1]


def test_conditional_mode_returns_given_robots_exactly(tiny):
    occ = np.zeros((140, 140), np.uint8)
    pos = np.array([[40.0, 40.0], [45.0, 40.0], [40.0, 46.0]])
    path = np.cumsum(np.full((16, 2), 0.7), axis=0) + pos[1]
    out = tiny.plan(occ, pos, leader=0, goal=(100, 100), fixed={1: path}, candidates=3, seed=1)
    assert out.shape == (3, 3, 16, 2)
    assert np.array_equal(out[:, 1], np.broadcast_to(path, (3, 16, 2)))
    assert not np.allclose(out[0, 0], out[1, 0]), "candidates differ"
    again = tiny.plan(occ, pos, 0, (100, 100), fixed={1: path}, candidates=3, seed=1)
    assert np.array_equal(out, again)


def test_noise_scale_is_the_sampling_temperature(tiny):
    """plan.noise_scale multiplies the initial noise of deterministic DDIM: near 0 every candidate is the same
    plan, at 1 the candidates are the model's own distribution."""
    from roken.data.condition import build_condition

    occ = np.zeros((140, 140), np.uint8)
    cond = build_condition(occ, np.array([[40.0, 40.0], [45.0, 40.0]]), 0, (100.0, 100.0), tiny.cfg, tokens=2)
    cold = tiny.sample([cond], 4, generators=[torch.Generator().manual_seed(0)], noise_scale=1e-6)[0]
    warm = tiny.sample([cond], 4, generators=[torch.Generator().manual_seed(0)])[0]
    assert np.abs(cold - cold[:1]).max() < 1e-3 < np.abs(warm - warm[:1]).max()


def test_a_map_off_the_canvas_is_fitted_and_mapped_back(tiny):
    occ = np.zeros((35, 50), np.uint8)  # scaled up 2x (canvas 140), then centred
    pos = np.array([[10.0, 10.0], [14.0, 12.0]])
    fixed_path = np.linspace(pos[1], pos[1] + [8, 0], 16)
    out = tiny.plan(occ, pos, 0, (40, 30), fixed={1: fixed_path}, seed=0)
    assert np.allclose(out[1], fixed_path)
    with pytest.raises(ValueError, match="cluster"):
        tiny.plan(np.zeros((140, 140)), np.random.rand(11, 2) * 100 + 20, 0, (10, 10))


def test_clusters_generate_every_robot_once_with_given_overlaps():
    rng = np.random.default_rng(0)
    for trial in range(30):
        N = int(rng.integers(2, 13))
        pos = np.cumsum(rng.uniform(-9, 9, (N, 2)), axis=0) + 70  # a chain: mostly connected
        leader = int(rng.integers(N))
        clusters = overlapping_clusters(pos, leader, 15.0, size=4, new=1)
        generated = np.concatenate([c.generated for c in clusters])
        assert sorted(generated.tolist()) == list(range(N)), "each robot generated exactly once"
        assert clusters[0].leader >= 0 and not clusters[0].fixed.any()
        planned = set(clusters[0].generated.tolist())
        for c in clusters:
            assert len(c.members) <= 4 and len(set(c.members.tolist())) == len(c.members)
            assert set(c.members[c.fixed].tolist()) <= planned, "conditions are robots planned before"
            if c is not clusters[0] and c.fixed.any():
                planned_before = len(planned)
                assert c.fixed.sum() >= min(3, planned_before) or len(c.generated) > 1
            planned |= set(c.generated.tolist())


def test_clustered_rollout_holds_earlier_robots_fixed(tiny):
    cfg = load_config(None, [])
    gm = generate_map(cfg.map, "eval", 0)
    tasks, _ = make_tasks(load_config(None, ["eval.episodes=1"]), [gm], 7)
    ro = RokenRollout(tiny, PlanConfig(cluster_size=4, cluster_new=1, batch_size=4, device="cpu"), cfg.task)
    from roken.plan.rollout import _Slot
    seen_given = []
    real = tiny.sample

    def spy(conds, *a, **k):
        out = real(conds, *a, **k)
        for c, o in zip(conds, out):
            f = c["traj_mask"] > 0
            seen_given.append(np.abs(o[:, f] - (c["start"][f][:, None] + np.cumsum(c["chunk"][f], 1) * 2.0)).max()
                              if f.any() else 0.0)
        return out

    tiny.sample = spy
    try:
        slot = _Slot(0, tasks[0][1], gm, ro)
        plan = ro.plan_step([slot])
    finally:
        tiny.sample = real
    assert plan.shape == (1, 7, 16, 2) and np.isfinite(plan).all()
    assert len(seen_given) >= 2 and max(seen_given) < 1e-4


def test_clustered_guidance_sees_every_robot_outside_the_cluster(tiny):
    """Each cluster's guidance gets the team's other robots: earlier clusters' plans at every move, later
    clusters' robots where they stand over the executed moves only."""
    cfg = load_config(None, [])
    gm = generate_map(cfg.map, "eval", 0)
    tasks, _ = make_tasks(load_config(None, ["eval.episodes=1"]), [gm], 7)
    pc = PlanConfig(cluster_size=4, cluster_new=1, batch_size=4, device="cpu", guide=True, select="safe",
                    candidates=2, guide_steps=2, guide_iters=1, guide_final_iters=1)
    ro = RokenRollout(tiny, pc, cfg.task)
    from roken.plan.rollout import _Slot
    seen, real = [], ro.outside
    ro.outside = lambda slots, clusters, planned, done: seen.append(
        (clusters[0], done[0].copy(), real(slots, clusters, planned, done))) or seen[-1][2]
    slot = _Slot(0, tasks[0][1], gm, ro)
    plan = ro.plan_step([slot])
    assert len(seen) == len(ro.clusters(slot.q, slot.task.leader)) >= 3
    for c, done, (pts, w) in seen:
        others = np.setdiff1d(np.arange(7), c.members)
        assert pts.shape == (1, 7 - len(c.members), 16, 2) and w.shape == pts.shape[:3]
        for k, o in enumerate(others):
            if done[o]:  # planned in an earlier cluster: its plan, every move
                assert np.array_equal(pts[0, k], plan[0, o]) and (w[0, k] == 1).all()
            else:  # a later cluster's robot: where it stands, the executed moves only
                assert np.allclose(pts[0, k], slot.q[o]) and w[0, k].tolist() == [1.0] * 2 + [0.0] * 14


def test_sensing_mask_hides_exactly_the_cells_beyond_the_range():
    pos = np.array([[20.3, 30.7], [60.0, 61.5]])
    seen = sensed_cells(pos, 140, 10.0)
    r, c = np.mgrid[:140, :140]
    d = np.min([np.hypot(c + 0.5 - x, r + 0.5 - y) for x, y in pos], axis=0)
    assert np.array_equal(seen, d <= 10.0)
    occ = (np.random.default_rng(0).random((140, 140)) < 0.3).astype(np.uint8)
    cond = build_condition(occ, pos, 0, np.array([100.0, 100.0]), SampleConfig(), seen=seen, tokens=2)
    assert np.array_equal(cond["map"][0], np.where(seen, occ, 0)), "unseen cells are shown as free"


def test_closed_loop_steps_are_clipped_and_reproducible(tiny):
    cfg = load_config(None, ["eval.episodes=3"])
    maps = [generate_map(cfg.map, "eval", i) for i in range(3)]
    tasks, _ = make_tasks(cfg, maps, 3)
    by_id = {m.map_id: m for m in maps}
    pc = PlanConfig(batch_size=2, sensing_range=12.0, accumulate=True, device="cpu")
    runs = []
    for _ in range(2):
        ro = RokenRollout(tiny, pc, cfg.task, cfg.expert)
        runs.append(dict((i, (p, info)) for i, p, info in ro.run([t for _, t in tasks], by_id)))
    assert sorted(runs[0]) == [0, 1, 2]
    for i, (p, info) in runs[0].items():
        steps = np.linalg.norm(np.diff(p.astype(np.float64), axis=0), axis=-1)
        assert steps.max() <= 0.5 + 1e-6, "no simulator step exceeds max_step (by its norm)"
        assert steps.max() > 0.3, "the random model does move"
        assert np.array_equal(p, runs[1][i][0]), "the same seed gives the same episode"
        assert np.array_equal(p[0], tasks[i][1].starts.astype(np.float32))
        assert info["plans"].shape == (len(info["plan_steps"]), 3, 16, 2)


def test_safe_selection_prefers_clean_candidates():
    occ = np.zeros((40, 40), np.uint8)
    occ[20:, 18:22] = 1
    padded = pad_for_clearance(occ)
    t = np.linspace(0, 1, 5)[:, None]
    clean = np.stack([np.array([5.0, 5.0]) + t * [10, 0], np.array([5.0, 9.0]) + t * [10, 0]])  # (2, 5, 2)
    crash = np.stack([np.array([5.0, 5.0]) + t * [15, 20], np.array([5.0, 9.0]) + t * [15, 20]])  # into the wall
    apart = np.stack([np.array([5.0, 5.0]) + t * [30, 0], np.array([5.0, 9.0]) + t * [0, 25]])  # out of range
    paths = np.stack([crash, apart, clean])
    v = violations(paths, padded, None, 1.0, 2.0, 15.0)
    assert v[2] == 0 and v[0] > 0 and v[1] > 0
    assert choose(v, np.array([20.0, 30.0, 10.0])) == 2, "a clean candidate beats more progress"
    # plan.verify_moves: only a prefix must be clean; the rest's violations rank before progress
    head = violations(paths[:, :, :2], padded, None, 1.0, 2.0, 15.0)
    late = v - head
    assert (late >= 0).all() and head[2] == 0 and late[0] > 0, "prefix + rest = the whole chunk's count"
    far = paths.copy()
    far[2, :, 2:] += [0.0, 40.0]  # the clean candidate's later points move out into the wall too
    vf = violations(far, padded, None, 1.0, 2.0, 15.0)
    hf = violations(far[:, :, :2], padded, None, 1.0, 2.0, 15.0)
    assert vf[2] > 0 and hf[2] == 0
    assert choose(hf, np.array([20.0, 30.0, 10.0]), vf - hf) == int(np.argmin(np.where(hf == 0, vf - hf, 1e9)))


def test_executed_points_are_what_the_episode_records_and_catch_what_points_miss(tiny):
    """plan.verify_steps: between two planned points two robots can pass closer than at either point; the
    simulator's steps (executed_points, exactly what _Slot.execute records) show it."""
    from roken.plan.rollout import _Slot, executed_points

    occ = np.zeros((40, 40), np.uint8)
    padded = pad_for_clearance(occ)
    q = np.array([[10.0, 10.0], [12.0, 12.0]])
    plan = np.repeat(q[:, None], 16, 1).copy()
    plan[0, 0], plan[1, 0] = [12.0, 12.0], [10.0, 10.0]  # the two swap places in one move: they meet half way
    plan[0, 1:], plan[1, 1:] = [12.0, 12.0], [10.0, 10.0]
    pts = np.concatenate([q[:, None], plan], 1)[None]
    assert violations(pts, padded, None, 1.0, 2.0, 15.0)[0] == 0  # 2.83 m apart at every planned point
    steps = executed_points(q, plan[None], 2, 4, 0.5)
    assert steps.shape == (1, 2, 8, 2) and violations(steps, padded, None, 1.0, 2.0, 15.0)[0] > 0
    cfg = load_config(None, [])
    gm = generate_map(cfg.map, "eval", 0)
    tasks, _ = make_tasks(load_config(None, ["eval.episodes=1"]), [gm], 3)
    slot = _Slot(0, tasks[0][1], gm, RokenRollout(tiny, PlanConfig(device="cpu"), cfg.task, cfg.expert))
    rng = np.random.default_rng(0)
    plans = slot.q[:, None] + np.cumsum(rng.uniform(-2.5, 2.5, (3, 16, 2)), 1)  # some moves beyond full speed
    want = executed_points(slot.q, plans[None], 2, 4, cfg.task.max_step)[0]
    slot.execute(plans)
    assert np.array_equal(np.asarray(slot.hist[1:], np.float32).transpose(1, 0, 2), want)


def test_team_progress_ranks_a_plan_that_brings_the_followers_along():
    from roken.plan.select import geodesic_field, progress, team_progress

    occ = np.zeros((40, 40), np.uint8)
    occ[10:30, 20] = 1  # a wall between the followers and the goal, open above and below
    goal = np.array([35.0, 20.0])
    field = geodesic_field(occ, goal)
    starts = np.array([[10.0, 20.0], [12.0, 18.0]])  # two followers behind the wall
    ends = np.stack([starts + [0.0, -5.0], starts, starts - [3.0, 0.0]])  # round the wall / hold / backwards
    free = team_progress(starts, ends, goal, field)
    assert free[0] > 0 and free[1] == 0 and free[2] < 0
    np.testing.assert_allclose(free, np.mean([progress(starts[i], ends[:, i], goal, field) for i in range(2)], 0))
    # straight-line progress calls the move round the wall a loss (it moves away from the goal's row)
    assert team_progress(starts, ends, goal)[0] < 0


def test_evaluate_refuses_a_team_larger_than_the_model_up_front(tmp_path):
    r = cli("evaluate.py", "--planner", "roken", "--checkpoint", str(ROOT / "models" / "roken-small-mixed"),
            "--robots", "12", "--episodes", "1", "--out", str(tmp_path / "e"), "--workers", "0")
    assert r.returncode == 2 and "--cluster-size" in r.stderr and not (tmp_path / "e").exists()
    r = cli("evaluate.py", "--planner", "roken", "--robots", "2", "--episodes", "1", "--out", str(tmp_path / "e"),
            "--workers", "0")
    assert r.returncode == 2 and "--checkpoint" in r.stderr and not (tmp_path / "e").exists()


def test_held_hits_counts_close_encounters_with_standing_robots():
    from roken.plan.select import held_hits

    paths = np.zeros((3, 2, 2, 2))
    paths[0, 0, 1] = [10.0, 10.5]  # candidate 0: robot 0 comes 0.5 m from the standing robot at move 1
    paths[1, :, 1] = [[20.0, 20.0], [10.0, 12.0]]  # candidate 1: 2 m away, clear
    paths[2, 1, :] = [[10.2, 10.0], [9.9, 10.0]]  # candidate 2: robot 1 at it at both points
    held = np.array([[10.0, 10.0]])
    assert held_hits(paths, held, 1.0).tolist() == [1, 0, 2]
    assert held_hits(paths, held[:0], 1.0).tolist() == [0, 0, 0]


def _descend(field: np.ndarray, cell: tuple[int, int]) -> list[tuple[int, int]]:
    """The cells of the steepest descent of a distance field from cell (r, c) to its zero."""
    path = [cell]
    while field[path[-1]] > 0:
        r, c = path[-1]
        nbrs = [(r + dr, c + dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr or dc)
                and 0 <= r + dr < field.shape[0] and 0 <= c + dc < field.shape[1]]
        path.append(min(nbrs, key=lambda n: field[n]))
        assert len(path) < field.size, "a distance field descends to its source"
    return path


def test_inflated_free_space_distance_keeps_clear_of_block_faces():
    from roken.plan.select import geodesic_field, inflated_graph
    from roken.world.geometry import signed_distance_field
    from roken.world.paths import GridGraph

    occ = np.zeros((40, 40), np.uint8)
    occ[14:26, 15:25] = 1  # a block between start and goal, open all round
    goal, start = np.array([35.5, 20.5]), (20, 4)  # goal (x, y); start cell (r, c) on the goal's row
    plain = geodesic_field(occ, goal)
    np.testing.assert_allclose(geodesic_field(occ, goal, GridGraph.build(occ == 0, np.ones(occ.shape))), plain)
    inflated = geodesic_field(occ, goal, inflated_graph(occ, 3.0, 5.0))
    free = occ == 0
    assert (inflated[free] >= plain[free] - 1e-4).all(), "inflation only lengthens distances"
    sdf = signed_distance_field(occ)
    clear = lambda f: min(sdf[c] for c in _descend(f, start))  # noqa: E731
    assert clear(plain) < 1.0, "the plain shortest path grazes the block's corners"
    assert clear(inflated) >= 2.5, "the inflated one goes round at the inflation's distance"
    gain = lambda r, c: inflated[r, c] - plain[r, c]  # noqa: E731
    assert gain(20, 36) < gain(13, 20), "cells at a block face gain more than open cells near the goal"


def test_rollout_goal_fields_use_the_inflated_distance(tiny):
    from roken.plan.rollout import _Slot

    cfg = load_config(None, ["eval.episodes=1"])
    gm = generate_map(cfg.map, "eval", 0)
    (_, task), = make_tasks(cfg, [gm], 1)[0]
    slots = []
    for inflate in (0.0, 3.0):
        pc = PlanConfig(select="geodesic", guide=True, candidates=2, device="cpu", geo_inflate=inflate)
        slots.append(_Slot(0, task, gm, RokenRollout(tiny, pc, cfg.task, cfg.expert)))
    free = gm.occupancy == 0
    for a, b in ((slots[0].geodesic, slots[1].geodesic), (slots[0].fields[1], slots[1].fields[1])):
        ok = free & np.isfinite(a) & (a < 1e4)
        assert (b[ok] >= a[ok] - 1e-4).all() and (b[ok] > a[ok] + 1.0).any()
    with pytest.raises(ValueError, match="plan.geo_inflate"):
        RokenRollout(tiny, PlanConfig(geo_inflate=-1.0, device="cpu"), cfg.task, cfg.expert)


def test_the_carried_plan_is_shifted_held_and_never_lost_to_worse_candidates(tiny):
    """plan.keep_previous: the last chosen plan minus its executed moves, end point held, is one more candidate,
    so a re-plan whose fresh candidates are all worse follows it instead of holding or backing off."""
    from roken.plan.clusters import Cluster
    from roken.plan.rollout import _Slot
    from roken.plan.select import progress

    cfg = load_config(None, ["eval.episodes=1"])
    gm = generate_map(cfg.map, "eval", 0)
    (_, task), = make_tasks(cfg, [gm], 3)[0]
    H, r = tiny.cfg.horizon, 2
    pc = PlanConfig(select="safe", candidates=2, device="cpu", replan_every=r, keep_previous=True)
    ro = RokenRollout(tiny, pc, cfg.task, cfg.expert)
    slot = _Slot(0, task, gm, ro)
    # a clean plan: the team translates 0.02 m per move toward the goal (starts are clean, the steps are tiny)
    toward = (task.goal - slot.q[task.leader]) / np.linalg.norm(task.goal - slot.q[task.leader])
    slot.last = (slot.q[:, None] + 0.02 * np.arange(1, H + 1)[None, :, None] * toward).astype(np.float32)
    c = Cluster(np.arange(3), np.array([False, True, False]), task.leader)
    fresh = np.full((3, H, 2), 7.0, np.float32)
    carried = slot.carried(c, fresh)
    np.testing.assert_array_equal(carried[[0, 2], :H - r], slot.last[[0, 2], r:])
    np.testing.assert_array_equal(carried[[0, 2], H - r:], np.repeat(slot.last[[0, 2], -1:], r, 1))
    np.testing.assert_array_equal(carried[1], fresh[1])  # a given robot keeps this re-plan's plan
    # the re-plan: the carried plan is clean, so the chosen one is clean and progresses at least as far
    mine = np.concatenate([slot.q[:, None], slot.carried(Cluster(np.arange(3), np.zeros(3, bool), task.leader),
                                                         fresh)], 1)[None]
    assert violations(mine, slot.padded_known, None, cfg.task.d_obs_min, cfg.task.d_coll_min,
                      cfg.task.comm_radius)[0] == 0
    chosen = ro.plan_step([slot])[0]
    path = np.concatenate([slot.q[:, None], chosen], 1)[None]
    assert violations(path, slot.padded_known, None, cfg.task.d_obs_min, cfg.task.d_coll_min,
                      cfg.task.comm_radius)[0] == 0 and slot.holds == 0
    q = slot.q[task.leader]
    assert progress(q, chosen[None, task.leader, -1], task.goal)[0] >= progress(q, mine[:, task.leader, -1],
                                                                                 task.goal)[0] - 1e-9
    np.testing.assert_array_equal(slot.last, chosen)  # remembered for the next re-plan
    # without it the same re-plan has only the tiny model's fresh candidates, none of them clean: the team holds
    off = RokenRollout(tiny, PlanConfig(select="safe", candidates=2, device="cpu", replan_every=r), cfg.task,
                       cfg.expert)
    held = _Slot(0, task, gm, off)
    np.testing.assert_allclose(off.plan_step([held])[0], np.repeat(held.q[:, None], H, 1), atol=1e-4)
    assert held.holds == 1 and not PlanConfig().keep_previous
