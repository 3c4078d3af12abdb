"""Verified selection among G candidate plans (beyond the paper, whose stated limitation is the missing safety
shield). Only what a deployed planner has is used: its known map (the sensed one under partial observation),
the team's positions and the goal; never the true map or the expert.

  none      the first candidate (plain Roken: one candidate, the paper's planner)
  safe      keep the candidates with no obstacle or inter-robot violation and a connected team at every
            planned point (start included); take the one whose leader makes the most straight-line progress
            toward the goal. With no clean candidate the team holds position for this re-plan (a safety
            stop; plan.fallback = "fewest" executes the candidate with the fewest violations instead).
            With plan.verify_moves = V > 0 only the first V moves must be clean (the ones the next re-plans
            execute); the rest of the chunk ranks the clean-prefix candidates by its violation count, then
            progress. The receding horizon re-plans those later moves anyway, and at a block face the model's
            late points graze the block in every candidate, which held the team for good.
  geodesic  the same filter, ranked by progress along the free-space (octile) distance to the goal on the
            known map, so a plan that enters a dead end scores below one that goes round the wall.
"""
from __future__ import annotations

import numpy as np

from ..world.geometry import clearance, signed_distance_field
from ..world.graph import connected
from ..world.paths import GridGraph

SELECTIONS = ("none", "safe", "geodesic")


def violations(paths: np.ndarray, padded: np.ndarray, others: np.ndarray | None, d_obs: float, d_coll: float,
               radius: float) -> np.ndarray:
    """(G,) violation counts of candidate plans paths (G, m, P, 2) (P points in time, start first) on the known
    map (pad_for_clearance of it); others (k, P, 2): robots already planned, which the plans must not hit and
    which count for connectivity."""
    G, m, P, _ = paths.shape
    obs = (clearance(padded, paths.reshape(-1, 2)) < d_obs).reshape(G, -1).sum(axis=1)
    team = paths if others is None or len(others) == 0 else \
        np.concatenate([paths, np.broadcast_to(others[None], (G,) + others.shape)], axis=1)
    t = team.transpose(0, 2, 1, 3)  # (G, P, n, 2)
    n = t.shape[2]
    d = np.linalg.norm(t[:, :, :, None] - t[:, :, None], axis=-1)  # (G, P, n, n)
    close = (d < d_coll) & ~np.eye(n, dtype=bool)
    close[:, :, m:, m:] = False  # two given robots are not this plan's fault
    inter = close.sum(axis=(1, 2, 3)) // 2
    disc = (~connected(d.reshape(-1, n, n), radius)).reshape(G, P).sum(axis=1) if n > 1 else np.zeros(G, int)
    return obs + inter + disc


def held_hits(paths: np.ndarray, held: np.ndarray, d_coll: float) -> np.ndarray:
    """(G,) close encounters of candidate plans paths (G, m, P, 2) with robots held where they stand, held (k, 2):
    the robots of later clusters (clustered rollout), which hold there when their own re-plan finds no clean
    candidate, so the moves executed before their re-plan must keep clear of them."""
    if len(held) == 0:
        return np.zeros(len(paths), int)
    d = np.linalg.norm(paths[:, :, :, None] - held[None, None, None], axis=-1)  # (G, m, P, k)
    return (d < d_coll).sum(axis=(1, 2, 3))


def inflated_graph(known_occupancy: np.ndarray, within: float, weight: float) -> GridGraph:
    """The free-cell graph whose cells closer than `within` metres to a known obstacle cost up to 1 + weight
    (linear in the shortfall; plan.geo_inflate, plan.geo_inflate_weight): the free-space distance then follows
    paths that keep clear of block corners, where the guidance's obstacle term would fight its goal pull."""
    sdf = signed_distance_field(known_occupancy)
    return GridGraph.build(known_occupancy == 0, 1.0 + weight * np.clip(1.0 - sdf / within, 0.0, 1.0))


def geodesic_field(known_occupancy: np.ndarray, goal: np.ndarray, graph: GridGraph | None = None) -> np.ndarray:
    """(H, W) octile distance to the goal's cell over the known free cells (inf on obstacles / unreachable);
    `graph`: the free-cell graph of known_occupancy when one is already built (GridMap.free_graph, or
    inflated_graph for clearance-costed distances)."""
    graph = graph or GridGraph.build(known_occupancy == 0)
    src = graph.nearest_node(np.asarray(goal, np.float64), search_all=True)
    return graph.field_grid(src) if src >= 0 else np.full(known_occupancy.shape, np.inf)


def lookup(field: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Values of a cell field (H, W) at the cells of points pts (..., 2), clamped to the grid."""
    H, W = field.shape
    r = np.clip(np.floor(pts[..., 1]).astype(int), 0, H - 1)
    c = np.clip(np.floor(pts[..., 0]).astype(int), 0, W - 1)
    return field[r, c]


def progress(start: np.ndarray, ends: np.ndarray, goal: np.ndarray, field: np.ndarray | None = None) -> np.ndarray:
    """(G,) leader progress from start (2,) to ends (G, 2): straight-line, or along `field` (geodesic)."""
    if field is None:
        return np.linalg.norm(start - goal) - np.linalg.norm(ends - goal, axis=-1)
    d0, d1 = lookup(field, start), lookup(field, ends)
    out = np.where(np.isfinite(d1), (d0 if np.isfinite(d0) else 0.0) - d1, -1e9)
    return out.astype(np.float64)


def team_progress(starts: np.ndarray, ends: np.ndarray, goal: np.ndarray, field: np.ndarray | None = None
                  ) -> np.ndarray:
    """(G,) mean progress toward the goal of robots from starts (f, 2) to ends (G, f, 2) (plan.select_team: the
    followers', added to the leader's so a plan that brings a lagging follower round a block ranks higher and
    the chain does not pull taut behind a leader that walks on)."""
    return np.mean([progress(starts[i], ends[:, i], goal, field) for i in range(len(starts))], axis=0)


def choose(viol: np.ndarray, prog: np.ndarray, late: np.ndarray | None = None) -> int:
    """Index of the best candidate: zero violations first (viol: in the verified moves), then fewest violations
    in the unverified rest (late, when given), then most progress."""
    keys = (-prog, viol) if late is None else (-prog, late, viol)
    return int(np.lexsort(keys)[0])
