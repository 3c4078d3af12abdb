"""The leader's sub-goal along the free-space path (plan.subgoal): in sight, on the path, within the lookahead."""
import numpy as np

from roken.plan.select import geodesic_field
from roken.plan.subgoal import descend, subgoal
from roken.world.geometry import clearance, pad_for_clearance


def _segment_clear(padded, a, b):
    t = np.linspace(0, 1, 200)[:, None]
    return (clearance(padded, a + t * (b - a)) > 0).all()


def test_open_map_gives_the_goal_or_a_point_on_the_straight_line():
    occ = np.zeros((140, 140), np.uint8)
    goal = np.array([100.5, 70.5])
    field, padded = geodesic_field(occ, goal), pad_for_clearance(occ)
    near = subgoal(field, padded, np.array([80.2, 70.3]), goal, 30.0)
    assert np.array_equal(near, goal)  # 20 m away and in sight: the goal itself
    far = subgoal(field, padded, np.array([20.2, 70.3]), goal, 30.0)
    assert 25.0 <= np.linalg.norm(far - [20.2, 70.3]) <= 30.0 and abs(far[1] - 70.5) <= 1.0


def test_a_wall_in_the_way_gives_a_subgoal_in_sight_round_it():
    occ = np.zeros((140, 140), np.uint8)
    occ[40:100, 60:64] = 1  # a wall x = 60..64, y = 40..100, between start and goal
    goal, start = np.array([90.5, 70.5]), np.array([50.3, 70.2])
    field, padded = geodesic_field(occ, goal), pad_for_clearance(occ)
    path = descend(field, start, 500)
    assert np.allclose(path[-1], goal)  # the descent reaches the goal's cell
    assert (clearance(padded, path) > 0).all()
    sg = subgoal(field, padded, start, goal, 30.0)
    assert _segment_clear(padded, start, sg)  # in sight of the leader
    assert not _segment_clear(padded, start, goal)
    assert field[int(sg[1]), int(sg[0])] < field[int(start[1]), int(start[0])]  # nearer the goal along the path
    assert np.min(np.linalg.norm(path - sg, axis=1)) < 1e-9  # a point of the path
    assert sg[1] < 41.0 or sg[1] > 99.0 or sg[0] < 60  # towards one of the wall's ends


def test_a_start_the_field_cannot_reach_falls_back_to_the_goal():
    occ = np.zeros((140, 140), np.uint8)
    occ[:, 60:64] = 1  # a wall across the map: the goal's side is cut off
    goal = np.array([90.5, 70.5])
    field = geodesic_field(occ, goal)
    assert not np.isfinite(field[20, 20])
    assert np.array_equal(subgoal(field, pad_for_clearance(occ), np.array([20.0, 20.0]), goal, 30.0), goal)
