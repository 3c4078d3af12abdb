"""The paper's episode metrics, exactly as ARCHITECTURE.md defines them; every planner is scored here.

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

from ..world.geometry import clearance
from ..world.graph import connected
from ..world.grid import GridMap
from ..world.paths import octile_length
from ..world.tasks import TaskConfig

METRIC_KEYS = ("full_success", "obstacle_collision", "inter_collision", "connectivity", "reach", "length")


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


def summarize(rows: list[EpisodeMetrics] | list[dict]) -> dict:
    """Mean of each metric over episodes; `length` over full-success episodes only (nan if none)."""
    def get(r, k):
        return r[k] if isinstance(r, dict) else getattr(r, k)

    n = len(rows)
    if n == 0:
        return {k: float("nan") for k in METRIC_KEYS} | {"episodes": 0}
    succ = np.array([get(r, "success") for r in rows], dtype=bool)
    ratios = np.array([get(r, "path_length") / get(r, "astar_length") if get(r, "astar_length") > 0
                       else np.nan for r in rows])
    return {
        "full_success": float(succ.mean()),
        "obstacle_collision": float(np.mean([get(r, "obstacle_collision") for r in rows])),
        "inter_collision": float(np.mean([get(r, "inter_collision") for r in rows])),
        "connectivity": float(np.mean([get(r, "connectivity") for r in rows])),
        "reach": float(np.mean([get(r, "reach") for r in rows])),
        "length": float(np.nanmean(ratios[succ])) if succ.any() else float("nan"),
        "episodes": n,
    }


def format_table(rows: list[tuple[str, dict]]) -> str:
    """Paper-style table: one row per (label, summary)."""
    head = f"{'planner':<22}{'N':>4}{'episodes':>10}{'full succ':>11}{'obs-coll':>10}{'inter-coll':>12}" \
           f"{'connect':>9}{'reach':>8}{'length':>8}"
    lines = [head, "-" * len(head)]
    for label, m in rows:
        name, _, n = label.rpartition("@")
        lines.append(f"{name:<22}{n:>4}{m['episodes']:>10d}{m['full_success']:>11.3f}"
                     f"{m['obstacle_collision']:>10.3f}{m['inter_collision']:>12.3f}{m['connectivity']:>9.3f}"
                     f"{m['reach']:>8.3f}{m['length']:>8.3f}")
    return "\n".join(lines)
