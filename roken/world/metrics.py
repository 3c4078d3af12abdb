"""The paper's per-episode metrics, exactly as ARCHITECTURE.md defines them. Every planner and the dataset
generator score episodes with this one function (it lives in `world` so that every stage may import it).

Per episode, from the recorded positions p[t, i], t = 0..T:
  obstacle_collision  some robot at some step is closer than d_obs_min to an occupied unit square
                      (outside the map is occupied)
  inter_collision     some pair at some step is closer than d_coll_min
  connectivity        at every step the disk graph (edges ||p_i - p_j|| <= R) is connected
  reach               the leader comes within eps_goal of the goal
  success             reach, no collision of either kind, always connected
  length              (success episodes) mean travelled length over robots / octile A* length from the
                      leader's start cell to the goal cell
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import clearance
from .graph import connected
from .grid import GridMap
from .paths import octile_length
from .tasks import TaskConfig


@dataclass
class EpisodeMetrics:
    success: bool
    reach: bool
    obstacle_collision: bool
    inter_collision: bool
    connectivity: bool
    path_length: float  # mean over robots of the travelled length (m)
    astar_length: float  # octile A* length, leader start cell -> goal cell (m)

    @property
    def length_ratio(self) -> float:
        return self.path_length / self.astar_length if self.astar_length > 0 else float("nan")


def episode_metrics(positions: np.ndarray, gm: GridMap, goal: np.ndarray, leader: int,
                    cfg: TaskConfig, astar_length: float | None = None) -> EpisodeMetrics:
    """Score one episode; positions (T+1, N, 2) in the map's coordinates."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[-1] != 2 or len(p) < 1:
        raise ValueError(f"positions must be (T+1, N, 2), got {p.shape}")
    T1, N, _ = p.shape
    obstacle = bool((clearance(gm.padded, p) < cfg.d_obs_min).any())
    dist = np.linalg.norm(p[:, :, None] - p[:, None], axis=-1)  # (T+1, N, N)
    off = ~np.eye(N, dtype=bool)
    inter = bool((dist[:, off] < cfg.d_coll_min).any()) if N > 1 else False
    conn = bool(connected(dist, cfg.comm_radius).all()) if N > 1 else True
    reach = bool((np.linalg.norm(p[:, leader] - goal, axis=-1) <= cfg.eps_goal).any())
    travelled = float(np.linalg.norm(np.diff(p, axis=0), axis=-1).sum(axis=0).mean()) if T1 > 1 else 0.0
    if astar_length is None:
        astar_length = octile_length(gm.occupancy == 0, p[0, leader], goal, gm.free_graph)
    success = reach and not obstacle and not inter and conn
    return EpisodeMetrics(success, reach, obstacle, inter, conn, travelled, float(astar_length))


def failure_reason(positions: np.ndarray, gm: GridMap, goal: np.ndarray, leader: int, cfg: TaskConfig) -> str | None:
    """Why an episode failed, at the first step it did (None for a full success): the first obstacle collision,
    inter-robot collision or disconnection, else a time-out (the goal never reached)."""
    p = np.asarray(positions, dtype=np.float64)
    T1, N, _ = p.shape
    events = []
    clear = clearance(gm.padded, p)  # (T+1, N)
    hit = np.argwhere(clear < cfg.d_obs_min)
    if len(hit):
        events.append((int(hit[0, 0]), f"obstacle collision at step {hit[0, 0]} (robot {hit[0, 1]})"))
    if N > 1:
        dist = np.linalg.norm(p[:, :, None] - p[:, None], axis=-1)
        iu = np.triu_indices(N, 1)
        close = np.argwhere(dist[:, iu[0], iu[1]] < cfg.d_coll_min)
        if len(close):
            t, k = close[0]
            events.append((int(t), f"inter-robot collision at step {t} (robots {iu[0][k]}, {iu[1][k]})"))
        apart = np.flatnonzero(~connected(dist, cfg.comm_radius))
        if len(apart):
            events.append((int(apart[0]), f"disconnected at step {apart[0]}"))
    if events:
        return min(events)[1]
    if not (np.linalg.norm(p[:, leader] - goal, axis=-1) <= cfg.eps_goal).any():
        return f"time-out after {T1 - 1} steps (goal not reached)"
    return None
