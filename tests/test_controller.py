"""RokenController: the deployable planner one re-plan at a time for user code."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from roken.config import load_config
from roken.eval.harness import make_tasks
from roken.plan import PlanConfig, RokenController, RokenRollout
from roken.plan.controller import rollout_config
from roken.world.maps import generate_map

ROOT = Path(__file__).resolve().parents[1]


def test_a_team_driven_by_the_controller_replays_the_evaluation_episode(tiny):
    """The controller runs the harness's own re-plan: with the deployable settings (guidance, geodesic ranking of
    verified candidates, every executed step checked, the carried plan) and the task's seed, replan() + step()
    give the very episode the closed-loop rollout records, step for step, holds included."""
    cfg = load_config(ROOT / "configs/deploy.yaml", ["eval.episodes=2", "expert.step_limit_factor=0.1",
                                                     "expert.step_limit_extra=40"])  # ~8 re-plans an episode
    maps = [generate_map(cfg.map, "eval", i) for i in range(2)]
    tasks, _ = make_tasks(cfg, maps, 3)
    by_id = {m.map_id: m for m in maps}
    pc = replace(rollout_config(cfg.plan, "roken+guided+geodesic"), device="cpu", guide_final_iters=5)
    ro = RokenRollout(tiny, replace(pc, batch_size=1), cfg.task, cfg.expert)
    ref = {i: (p, info) for i, p, info in ro.run([t for _, t in tasks], by_id)}
    ctl = RokenController(tiny, pc, cfg.task, cfg.expert)
    for i, (_, task) in enumerate(tasks):
        team = ctl.start(by_id[task.map_id].occupancy, task.starts, task.leader, task.goal, seed=task.seed)
        assert np.allclose(team.positions, task.starts)
        while not team.finished:
            plan = team.replan()
            assert plan.shape == (3, 16, 2)
            team.step()
        assert np.array_equal(team.history.astype(np.float32), ref[i][0])
        assert team.holds == ref[i][1]["holds"] and team.reached == ref[i][1]["reached"]


def test_a_map_updated_as_the_robots_sense_it_gives_the_partial_observation_episode(tiny):
    """A team that maps while it drives: the user passes the map as known after each re-plan's moves (cells within
    12 m of a robot so far, the rest free) and gets the harness's partial-observation episode (plan.sensing_range
    12, accumulate) step for step; only the step limit differs (the reference path on the map known at the start)."""
    from roken.data.condition import known_occupancy, sensed_cells

    cfg = load_config(ROOT / "configs/deploy.yaml", ["eval.episodes=2", "expert.step_limit_factor=0.1",
                                                     "expert.step_limit_extra=40"])
    gm = generate_map(cfg.map, "eval", 0)
    (_, task), = make_tasks(cfg, [gm], 3)[0][:1]
    pc = replace(rollout_config(cfg.plan, "roken+guided+geodesic"), device="cpu", guide_final_iters=5)
    ro = RokenRollout(tiny, replace(pc, batch_size=1, sensing_range=12.0, accumulate=True), cfg.task, cfg.expert)
    (_, ref, _), = ro.run([task], {gm.map_id: gm})
    seen = sensed_cells(task.starts, 140, 12.0)
    team = RokenController(tiny, pc, cfg.task, cfg.expert).start(known_occupancy(gm.occupancy, seen), task.starts,
                                                                 task.leader, task.goal, seed=task.seed)
    while not team.finished:
        team.replan()
        seen |= sensed_cells(team.step(), 140, 12.0)
        team.update(occupancy=known_occupancy(gm.occupancy, seen))
    m = min(len(ref), len(team.history))
    assert m > 40 and np.array_equal(team.history[:m].astype(np.float32), ref[:m])


def test_a_map_off_the_canvas_plans_and_updates_in_its_own_metres(tiny):
    """A 35 x 50 m map keeps its metres (centred on the 140 m canvas; with rescale=True it is scaled 2x as the map
    loaders fit maps): plans, positions and the history come back in the map's own metres, update() accepts where
    the robots are now or every simulator step since, and a simulated step is at most 0.5 m of the map."""
    ctl = RokenController(tiny, PlanConfig(device="cpu", select="safe", candidates=4), load_config().task)
    occ = np.zeros((35, 50), np.uint8)
    occ[20:24, 30:34] = 1
    pos = np.array([[6.0, 6.0], [9.0, 6.0]])
    for rescale, max_step in ((False, 0.5), (True, 0.25)):
        team = ctl.start(occ, pos, leader=0, goal=(44, 30), seed=3, rescale=rescale)
        assert team.fit.scale == (2.0 if rescale else 1.0)
        plan = team.replan()
        assert plan.shape == (2, 16, 2)
        if team.held:  # no clean candidate: the plan is the safety stop, in the map's metres
            assert np.allclose(plan, pos[:, None])
        team.step()
        assert np.linalg.norm(np.diff(team.history, axis=0), axis=-1).max() <= max_step + 1e-4
        again = ctl.start(occ, pos, 0, (44, 30), seed=3, rescale=rescale).replan()
        assert np.array_equal(again, plan), "the same seed and inputs give the same plan"
    team = ctl.start(occ, pos, 0, (44, 30))
    team.update(pos + [0.5, 0.25])  # only where they are now: straight lines over the 8 executed steps
    assert team.history.shape == (1 + 8, 2, 2) and np.allclose(team.positions, pos + [0.5, 0.25])
    assert np.allclose(team.history[4], pos + [0.25, 0.125])
    steps = pos + np.linspace(0.6, 1.0, 3)[:, None, None]
    team.update(steps)  # every simulator step since
    assert team.history.shape == (1 + 8 + 3, 2, 2) and np.allclose(team.history[-3:], steps)
    seen = occ.copy()
    seen[10:14, 16:20] = 1  # a block the robots have just seen, ahead of them
    before = team._slot.padded_known.copy()
    team.update(team.positions, occupancy=seen)  # verified selection checks the next candidates on it
    x, y = team.fit.to_canvas([17.5, 11.5]).astype(int)
    assert team._slot.gm.occupancy[y, x] == 1 and not np.array_equal(team._slot.padded_known, before)
    with pytest.raises(ValueError, match=r"the map of this team is \(35, 50\)"):
        team.update(team.positions, occupancy=np.zeros((40, 50)))
    with pytest.raises(ValueError, match="150 x 150 m map is larger than the model's 140 x 140 m canvas"):
        ctl.start(np.zeros((150, 150)), pos, 0, (44, 30))
    far = np.array([[6.0, 6.0], [12.0, 6.0]])  # 3 m on the half-scale canvas: spacing holds there, not in the map
    assert ctl.start(np.zeros((150, 150)), far, 0, (44, 30), rescale=True).fit.scale == 0.5


def test_the_controller_refuses_bad_inputs_naming_them(tiny):
    ctl = RokenController(tiny, PlanConfig(device="cpu"), load_config().task)
    occ = np.zeros((140, 140), np.uint8)
    pos = np.array([[40.0, 40.0], [44.0, 40.0]])
    with pytest.raises(ValueError, match="leader 2"):
        ctl.start(occ, pos, 2, (100, 100))
    with pytest.raises(ValueError, match="goal: outside the map"):
        ctl.start(occ, pos, 0, (150, 100))
    with pytest.raises(ValueError, match=r"positions: \(n, 2\)"):
        ctl.start(occ, pos.ravel(), 0, (100, 100))
    eleven = np.array([[40.0 + 3 * (i % 4), 40.0 + 3 * (i // 4)] for i in range(11)])
    with pytest.raises(ValueError, match="cluster-size"):
        ctl.start(occ, eleven, 0, (100, 100))
    clustered = RokenController(tiny, PlanConfig(device="cpu", cluster_size=4), load_config().task)
    assert clustered.start(occ, eleven, 0, (100, 100)).replan().shape == (11, 16, 2)  # more robots than tokens
    blocked = occ.copy()
    blocked[39:42, 43:46] = 1  # robot 1 stands in a block: every verified candidate would fail at its start
    with pytest.raises(ValueError, match="start refused: robot 1 is .* from an obstacle .*d_obs_min=1 m"):
        ctl.start(blocked, pos, 0, (100, 100))
    with pytest.raises(ValueError, match="start refused: two robots start 1.00 m apart"):
        ctl.start(occ, [[40, 40], [41, 40]], 0, (100, 100))
    with pytest.raises(ValueError, match="start refused: the goal is in an obstacle cell"):
        ctl.start(blocked, [[40, 60], [44, 60]], 0, (44, 40.5))
    team = ctl.start(occ, pos, 0, (100, 100))
    with pytest.raises(RuntimeError, match="replan"):
        team.step()
    with pytest.raises(ValueError, match=r"\(k, 2, 2\)"):
        team.update(np.zeros((3, 2)))


def test_load_takes_the_row_and_settings_of_a_config():
    ctl = RokenController.load(ROOT / "models/roken-cpu-four-dagger", ROOT / "configs/deploy.yaml", device="cpu")
    pc = ctl.plan
    assert (pc.guide, pc.select, pc.candidates, pc.verify_steps, pc.keep_previous, pc.geo_inflate) == \
        (True, "geodesic", 8, True, True, 3.0)
    plain = RokenController.load(ROOT / "models/roken-cpu-four-dagger", row="roken", device="cpu")
    assert (plain.plan.guide, plain.plan.select, plain.plan.candidates) == (False, "none", 1)
    with pytest.raises(ValueError, match="a Roken row"):
        RokenController.load(ROOT / "models/roken-cpu-four-dagger", row="laplacian", device="cpu")
