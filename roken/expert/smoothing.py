"""Trajectory smoothing with a constraint re-check (paper: "We smooth the expert trajectories")."""
from __future__ import annotations

import numpy as np

from ..world.geometry import clearance
from ..world.graph import connected
from ..world.grid import GridMap
from ..world.tasks import Task, TaskConfig


def moving_average(p: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average over time of p (T+1, ...), the window shrinking symmetrically at both ends
    so the first and last positions are kept exactly. A step of the result is an average of original
    steps, so it is never longer than the longest original step."""
    T1 = len(p)
    half = window // 2
    if half == 0 or T1 < 3:
        return p.copy()
    c = np.concatenate([np.zeros((1,) + p.shape[1:]), np.cumsum(p, axis=0, dtype=np.float64)])
    t = np.arange(T1)
    h = np.minimum(np.minimum(t, T1 - 1 - t), half)
    return ((c[t + h + 1] - c[t - h]) / (2 * h + 1)[:, None, None]).astype(p.dtype)


def violations(p: np.ndarray, gm: GridMap, tc: TaskConfig) -> np.ndarray:
    """(obstacle, inter, disconnected) flags of positions p (T+1, N, 2)."""
    N = p.shape[1]
    obs = bool((clearance(gm.padded, p.astype(np.float64)) < tc.d_obs_min).any())
    d = np.linalg.norm(p[:, :, None] - p[:, None], axis=-1)
    inter = bool((d[:, ~np.eye(N, dtype=bool)] < tc.d_coll_min).any()) if N > 1 else False
    disc = bool((~connected(d, tc.comm_radius)).any()) if N > 1 else False
    return np.array([obs, inter, disc])


def smooth_episode(raw: np.ndarray, gm: GridMap, task: Task, tc: TaskConfig, window: int):
    """Smoothed positions if smoothing adds no violation and keeps the leader's reach; else the raw ones.

    Returns (positions float32, whether the smoothed version was kept).
    """
    if window <= 1:
        return raw.astype(np.float32), False
    sm = moving_average(raw.astype(np.float64), window)
    before = violations(raw, gm, tc)
    after = violations(sm, gm, tc)
    reach_raw = (np.linalg.norm(raw[:, task.leader] - task.goal, axis=-1) <= tc.eps_goal).any()
    reach_sm = (np.linalg.norm(sm[:, task.leader] - task.goal, axis=-1) <= tc.eps_goal).any()
    if (after & ~before).any() or (reach_raw and not reach_sm):
        return raw.astype(np.float32), False
    return sm.astype(np.float32), True
