"""The leader's reference: octile A* on safe cells, string-pulled with clearance, resampled finely."""
from __future__ import annotations

import numpy as np

from ..world.grid import GridMap
from ..world.paths import cell_path, path_length, resample, shortcut


def leader_reference(gm: GridMap, start: np.ndarray, goal: np.ndarray, clearance: float,
                     spacing: float) -> np.ndarray | None:
    """Smoothed A* reference from `start` to `goal` as points every `spacing` m; None if unreachable.

    The search runs on safe cells (3 x 3 free, centre clearance >= 1.5 m), so the raw path keeps the
    robots clear of obstacles; string pulling then removes the grid's zig-zag while keeping `clearance`.
    """
    g = gm.safe_graph
    s, t = g.nearest_node(start, search_all=True), g.nearest_node(goal, search_all=True)
    if s < 0 or t < 0 or g.component[s] != g.component[t]:
        return None
    _, pred = g.field(t, with_predecessors=True)
    cells = cell_path(g, pred, s)  # start cell ... goal cell
    poly = np.concatenate([np.asarray(start, float)[None], cells, np.asarray(goal, float)[None]])
    poly = shortcut(poly, gm.sdf, clearance)
    return resample(poly, spacing)
