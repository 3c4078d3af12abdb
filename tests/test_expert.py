import numpy as np

from roken.expert.laplacian import ExpertConfig, LaplacianExpert
from roken.expert.smoothing import moving_average
from roken.eval.metrics import episode_metrics, summarize
from roken.world.maps import generate_map
from roken.world.tasks import sample_task


def _run(mc, tc, n, idx, cfg=None):
    maps = {}
    tasks = []
    for i in idx:
        gm = generate_map(mc, "eval", i)
        maps[gm.map_id] = gm
        tasks.append(sample_task(gm, n, tc, np.random.default_rng([5, n, i])))
    out = dict(LaplacianExpert(cfg or ExpertConfig(batch_size=8), tc).run(tasks, maps))
    return tasks, maps, [out[i] for i in range(len(tasks))]


def test_expert_succeeds_on_a_small_batch(mc, tc):
    tasks, maps, eps = _run(mc, tc, 4, range(10))
    rows = [episode_metrics(e.positions, maps[t.map_id], t.goal, t.leader, tc) for t, e in zip(tasks, eps)]
    s = summarize(rows)
    assert s["full_success"] >= 0.8, s
    assert s["obstacle_collision"] == 0 and s["inter_collision"] == 0
    for t, e in zip(tasks, eps):
        p = e.positions
        np.testing.assert_allclose(p[0], t.starts, atol=1e-5)  # recorded from the start
        steps = np.linalg.norm(np.diff(p, axis=0), axis=-1)
        assert steps.max() <= tc.max_step + 1e-4  # every step <= 0.5 m
        assert len(p) - 1 <= e.info["limit"]


def test_expert_is_deterministic(mc, tc):
    # batch 3 < 4 tasks: a finished slot is refilled, which must not perturb the other slots
    _, _, a = _run(mc, tc, 3, range(4), ExpertConfig(batch_size=3))
    _, _, b = _run(mc, tc, 3, range(4), ExpertConfig(batch_size=3))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.positions, y.positions)


def test_warm_start_takes_the_first_command_as_the_previous_step(mc, tc):
    # expert.warm_start: the first step is the undamped command (as with no inertia), from rest it is damped;
    # batch 3 < 4 tasks: a refilled slot starts warm too
    def first_steps(**kw):
        _, _, eps = _run(mc, tc, 3, range(4), ExpertConfig(batch_size=3, smooth_window=1, **kw))
        return np.stack([e.positions[1] - e.positions[0] for e in eps])

    warm, undamped, rest = first_steps(warm_start=True), first_steps(inertia=0.0), first_steps()
    np.testing.assert_allclose(warm, undamped, atol=1e-5)
    assert np.linalg.norm(rest, axis=-1).mean() < 0.75 * np.linalg.norm(warm, axis=-1).mean()


def test_single_robot_and_large_team(mc, tc):
    tasks, maps, eps = _run(mc, tc, 1, range(2))
    assert all(e.reached for e in eps)
    tasks, maps, eps = _run(mc, tc, 10, range(2))
    for t, e in zip(tasks, eps):
        m = episode_metrics(e.positions, maps[t.map_id], t.goal, t.leader, tc)
        assert not m.obstacle_collision and not m.inter_collision and m.connectivity


def test_moving_average_keeps_endpoints_and_step_bound():
    rng = np.random.default_rng(0)
    steps = rng.normal(size=(50, 3, 2))
    steps *= 0.5 / np.linalg.norm(steps, axis=-1, keepdims=True)
    p = np.concatenate([np.zeros((1, 3, 2)), np.cumsum(steps, axis=0)])
    s = moving_average(p, 5)
    np.testing.assert_allclose(s[0], p[0])
    np.testing.assert_allclose(s[-1], p[-1])
    assert np.linalg.norm(np.diff(s, axis=0), axis=-1).max() <= 0.5 + 1e-9


def test_cautious_config_keeps_more_clearance_and_still_solves(mc, tc):
    # configs/expert/cautious.yaml (README "A cautious expert"): the obstacle factor full at 2.4 m pushes the team
    # off block faces; the lowered slow-down thresholds keep the leader moving. Same tasks as the default.
    from pathlib import Path
    from roken.config import load_config
    from roken.world.geometry import clearance
    cfg = load_config(Path(__file__).parents[1] / "configs" / "expert" / "cautious.yaml", ["expert.batch_size=8"])
    assert (cfg.expert.obs_full, cfg.expert.leader_slow, cfg.expert.leader_stop) == (2.4, 0.2, 0.04)
    p10 = {}
    for name, ec in (("default", ExpertConfig(batch_size=8)), ("cautious", cfg.expert)):
        tasks, maps, eps = _run(mc, tc, 4, range(10), ec)
        rows = [episode_metrics(e.positions, maps[t.map_id], t.goal, t.leader, tc) for t, e in zip(tasks, eps)]
        s = summarize(rows)
        assert s["full_success"] >= 0.7 and s["obstacle_collision"] == 0 and s["inter_collision"] == 0, (name, s)
        c = np.concatenate([clearance(maps[t.map_id].padded, e.positions.reshape(-1, 2).astype(np.float64))
                            for t, e in zip(tasks, eps)])
        p10[name] = np.percentile(c, 10)
    assert p10["cautious"] > p10["default"] + 0.2, p10


def test_dart_approach_closes_a_pair_and_the_expert_recovers(mc, tc):
    # expert.disturb_mode=approach (README "DART"): one robot walks at its nearest team-mate, which holds, so the
    # pair ends the push far closer than the expert keeps its robots (the safety filter still stops it short of
    # d_coll_min); the expert then finishes the episode cleanly from there. Without a push nothing changes.
    import dataclasses
    import pytest
    push = ExpertConfig(batch_size=8, disturb=0.25, disturb_steps=16, disturb_mode="approach")
    runs = {name: _run(mc, tc, 4, range(10), ec)
            for name, ec in (("none", ExpertConfig(batch_size=8)), ("approach", push))}
    for name, (tasks, maps, eps) in runs.items():
        rows = [episode_metrics(e.positions, maps[t.map_id], t.goal, t.leader, tc) for t, e in zip(tasks, eps)]
        s = summarize(rows)
        assert s["full_success"] >= 0.7 and s["obstacle_collision"] == 0 and s["inter_collision"] == 0, (name, s)
    ats = [e.info["disturbed_at"] for e in runs["approach"][2]]
    assert all(a >= 0 for a in ats) and all(e.info["disturbed_at"] == -1 for e in runs["none"][2])
    closest = {}
    for name, (_, _, eps) in runs.items():  # the team at the push's end (the same step in both runs)
        ends = [e.positions[min(a + 16, len(e.positions) - 1)] for a, e in zip(ats, eps)]
        closest[name] = np.median([np.min(np.linalg.norm(q[:, None] - q[None], axis=-1) + 99 * np.eye(4))
                                   for q in ends])
    assert closest["approach"] < 3.2 < closest["none"], closest
    with pytest.raises(ValueError, match="disturb_mode"):
        LaplacianExpert(dataclasses.replace(ExpertConfig(), disturb_mode="toward"), tc)
