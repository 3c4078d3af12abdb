"""A sub-goal for the leader along the free-space shortest path on the known map (`plan.subgoal`, off by default).

Watching the time-outs of the deployable planner: at a block between the leader and the goal, the model's
samples for the leader run straight at the goal, through the block (every candidate's leader points lie inside
it), guidance cannot pull 10-20 m of chunk round the block, verified selection rejects every candidate and the
team holds for good. The model was trained with goals along the leader's own future path (`samples.final_goal_prob`:
half the goals are a point the expert's leader passed), so a nearer goal that the leader can see is in its
training distribution. This module gives it one, the way a local planner is fed by a global one:

  1. the free-space shortest path from the leader's cell to the goal's: steepest descent of the octile distance
     field (select.geodesic_field, the one geodesic selection ranks by), 8-connected;
  2. the sub-goal is the farthest point of that path, within `plan.subgoal` metres of path length, such that
     the straight segment from the leader to it and to every path point before it stays out of obstacle cells
     (string pulling, as pure-pursuit trackers do); the goal itself when it is that close and in sight.

Only what a deployed planner has is used (its known map and its goal); the metrics still score the task's goal.
Measured (README, sampler levers): every candidate is clean at such states, but the model creeps toward a near
sub-goal and time-outs replace the holds; no variant beat the task's goal on 64 `val` tasks, so it stays off.
"""
from __future__ import annotations

import numpy as np

from ..world.geometry import clearance

_NEIGHBOURS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)])


def descend(field: np.ndarray, start: np.ndarray, max_cells: int) -> np.ndarray:
    """(k, 2) cell centres (x, y metres) of the steepest-descent path of an octile distance field (H, W; inf on
    blocked cells) from the cell of start, at most max_cells cells, ending where no neighbour is lower."""
    H, W = field.shape
    r, c = int(np.clip(np.floor(start[1]), 0, H - 1)), int(np.clip(np.floor(start[0]), 0, W - 1))
    out = []
    here = field[r, c]
    for _ in range(max_cells):
        nb = np.array([r, c]) + _NEIGHBOURS
        ok = (nb[:, 0] >= 0) & (nb[:, 0] < H) & (nb[:, 1] >= 0) & (nb[:, 1] < W)
        nb = nb[ok]
        vals = field[nb[:, 0], nb[:, 1]]
        k = int(np.argmin(vals))
        if not vals[k] < here:  # the goal's cell (0), or a start the field cannot reach
            break
        r, c, here = int(nb[k, 0]), int(nb[k, 1]), vals[k]
        out.append((c + 0.5, r + 0.5))
    return np.asarray(out, np.float64).reshape(-1, 2)


def subgoal(field: np.ndarray, padded: np.ndarray, start: np.ndarray, goal: np.ndarray, lookahead: float,
            sample: float = 0.5, sight: bool = True) -> np.ndarray:
    """(2,) the leader's sub-goal (module docstring); the goal when the field gives no path from start;
    sight=False: the path point at the lookahead, in sight or not."""
    start, goal = np.asarray(start, np.float64), np.asarray(goal, np.float64)
    path = descend(field, start, int(np.ceil(lookahead)) + 2)  # a cell step is >= 1 m of path
    if len(path) == 0:
        return goal
    length = np.cumsum(np.linalg.norm(np.diff(np.vstack([start, path]), axis=0), axis=1))
    path = path[length <= lookahead]
    r, c = int(np.floor(goal[1])), int(np.floor(goal[0]))
    reached = 0 <= r < field.shape[0] and 0 <= c < field.shape[1] and len(path) > 0 and \
        np.floor(path[-1, 1]) == r and np.floor(path[-1, 0]) == c
    if reached:  # the goal itself ends the path
        path = np.vstack([path[:-1], goal])
    if len(path) == 0:
        return goal
    if not sight:
        return path[-1]
    # sight lines from start to every path point, sampled every `sample` metres: a point inside an obstacle cell
    # has clearance 0
    n = int(np.ceil(lookahead / sample)) + 1
    t = np.linspace(0.0, 1.0, n)[None, :, None]
    pts = start[None, None] + t * (path[:, None] - start[None, None])  # (k, n, 2)
    seen = (clearance(padded, pts.reshape(-1, 2)) > 0).reshape(len(path), n).all(axis=1)
    k = len(path) if seen.all() else int(np.argmin(seen))  # the first path point out of sight
    return path[max(k - 1, 0)]
