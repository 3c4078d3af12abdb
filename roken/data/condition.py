"""The model's condition: one world state -> the DiT's inputs (ARCHITECTURE.md, "The model's condition").

Training samples (`make_sample`), the planner (`roken.plan`) and GRPO prompts all call `build_condition`, so
what the model sees at training and at inference cannot drift apart. For T robot tokens (T >= n robots; the
rest is padding) and the canvas side S:

  start      (T, 2)     positions in metres (the token's PE and the origin of a relative chunk)
  rel_goal   (T, 2)     (goal - start) / (S / 2) for the leader, 0 for every other robot
  goal       (2,)       the goal in metres (0 when none is given)
  goal_mask  (T,)       1 for the leader
  traj_mask  (T,)       1 for robots whose chunk is given (conditional mode, clustered rollout)
  robot_mask (T,)       True for real robots
  chunk      (T, H, 2)  the given chunks in the model's representation (0 for generated robots and padding)
  prev_move  (T, 2)     each robot's last chunk move: (position - position `interval` simulator steps earlier) /
                        (interval * max_step), the chunk's own units (0 at an episode's start and for padding).
                        Read only by a model with `model.prev_move` (the expert's next move depends on its
                        inertia, which positions alone do not show)
  map        (3, S, S)  occupancy as the robots know it, start heat-map, goal heat-map (0 without a leader)

A sensing mask (S, S) bool marks the cells the team has seen; unseen cells are shown as free (the paper's
zero-shot partial-observation setting). The true occupancy is never changed, so metrics use the true map.
"""
from __future__ import annotations

import numpy as np

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .samples import SampleConfig

CONDITION_KEYS = ("start", "rel_goal", "goal", "goal_mask", "traj_mask", "robot_mask", "chunk", "map", "prev_move")

def heatmap(points: np.ndarray, size: int, sigma: float) -> np.ndarray:
    """(S, S) max over points (n, 2) of Gaussian kernels evaluated at cell centres."""
    c = np.arange(size, dtype=np.float32) + 0.5
    gx = np.exp(-((c[None, :] - points[:, :1]) ** 2) / (2 * sigma ** 2))  # (n, S)
    gy = np.exp(-((c[None, :] - points[:, 1:]) ** 2) / (2 * sigma ** 2))  # (n, S)
    return (gy[:, :, None] * gx[:, None, :]).max(axis=0).astype(np.float32)


def encode_chunk(points: np.ndarray, cfg: "SampleConfig") -> np.ndarray:
    """(H+1, N, 2) positions at t, t+interval, ... -> (N, H, 2) chunk in cfg.representation."""
    if cfg.representation == "relative":
        chunk = np.diff(points, axis=0) / cfg.step_scale
    else:
        chunk = points[1:] / cfg.pos_scale - 1.0
    return chunk.transpose(1, 0, 2).astype(np.float32)


def decode_chunk(chunk: np.ndarray, start: np.ndarray, cfg: "SampleConfig") -> np.ndarray:
    """(..., H, 2) chunk and (..., 2) start -> (..., H, 2) positions in metres (numpy; the model has a torch twin)."""
    if cfg.representation == "relative":
        return start[..., None, :] + np.cumsum(chunk, axis=-2) * cfg.step_scale
    return (chunk + 1.0) * cfg.pos_scale


def sensed_cells(positions: np.ndarray, size: int, sensing_range: float) -> np.ndarray:
    """(S, S) bool: cells whose centre lies within sensing_range of some robot at positions (n, 2)."""
    c = np.arange(size, dtype=np.float64) + 0.5
    dx = (c[None, :] - positions[:, :1]) ** 2  # (n, S) over columns
    dy = (c[None, :] - positions[:, 1:]) ** 2  # (n, S) over rows
    return ((dy[:, :, None] + dx[:, None, :]) <= sensing_range ** 2).any(axis=0)


def known_occupancy(occupancy: np.ndarray, seen: np.ndarray | None) -> np.ndarray:
    """What the team knows: the occupancy on seen cells, free elsewhere (seen None = the whole map)."""
    return occupancy if seen is None else np.where(seen, occupancy, 0).astype(occupancy.dtype)


def build_condition(occupancy: np.ndarray, positions: np.ndarray, leader: int, goal: np.ndarray | None,
                    cfg: "SampleConfig", given: np.ndarray | None = None, fixed: np.ndarray | None = None,
                    seen: np.ndarray | None = None, tokens: int | None = None,
                    previous: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """One world state as the model's inputs (module docstring).

    occupancy (S, S) on the canvas; positions (n, 2) metres; leader in 0..n-1, or -1 when no robot holds the
    goal (a later cluster of clustered rollout); given (n, H, 2) planned positions in metres of the robots
    marked in fixed (n,) bool (rows of other robots are ignored); seen (S, S) bool or None; tokens >= n robot
    slots (default samples.max_robots); previous (n, 2) the positions `interval` simulator steps earlier (None:
    at rest)."""
    S, H = cfg.canvas, cfg.horizon
    positions = np.asarray(positions, dtype=np.float32).reshape(-1, 2)
    n = len(positions)
    T = cfg.max_robots if tokens is None else tokens
    if occupancy.shape != (S, S):
        raise ValueError(f"occupancy is {occupancy.shape}, the model's canvas is {S} x {S}; fit the map first "
                         f"(roken.world.loaders.fit_to_canvas)")
    if n > T:
        raise ValueError(f"{n} robots but {T} robot tokens (samples.max_robots); plan a larger team with "
                         f"clustered rollout (--cluster-size 4)")
    if leader >= n:
        raise ValueError(f"leader {leader} is not one of the {n} robots")
    out = {
        "start": np.zeros((T, 2), np.float32), "rel_goal": np.zeros((T, 2), np.float32),
        "goal": np.zeros(2, np.float32), "goal_mask": np.zeros(T, np.float32), "traj_mask": np.zeros(T, np.float32),
        "robot_mask": np.zeros(T, bool), "chunk": np.zeros((T, H, 2), np.float32),
        "map": np.zeros((3, S, S), np.float32), "prev_move": np.zeros((T, 2), np.float32),
    }
    out["start"][:n] = positions
    if previous is not None:
        out["prev_move"][:n] = (positions - np.asarray(previous, np.float32).reshape(n, 2)) / cfg.step_scale
    out["robot_mask"][:n] = True
    if fixed is not None and np.any(fixed):
        fixed = np.asarray(fixed, dtype=bool)
        out["traj_mask"][:n] = fixed
        if given is None:
            raise ValueError("fixed robots need their given trajectories (given)")
        pts = np.concatenate([positions[None, fixed], np.asarray(given, np.float32)[fixed].transpose(1, 0, 2)])
        out["chunk"][np.flatnonzero(fixed)] = encode_chunk(pts, cfg)
    out["map"][0] = known_occupancy(occupancy, seen)
    out["map"][1] = heatmap(positions, S, cfg.heatmap_sigma)
    if goal is not None:
        goal = np.asarray(goal, dtype=np.float32).reshape(2)
        out["goal"] = goal
    if leader >= 0 and goal is not None:  # the goal is shown only to a (sub-)team that holds the leader
        out["rel_goal"][leader] = (goal - positions[leader]) / cfg.pos_scale
        out["goal_mask"][leader] = 1.0
        out["map"][2] = heatmap(goal[None], S, cfg.heatmap_sigma)
    return out
