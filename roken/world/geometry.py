"""Distance fields, exact clearance, bilinear lookup and line of sight on occupancy grids.

Conventions (ARCHITECTURE.md): 1 cell = 1 m, a position is (x, y) with x along columns and y along rows,
cell (r, c) is the unit square [c, c+1) x [r, r+1), occupancy == 1 is an obstacle and everything outside
the map is an obstacle.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt

# How many cells around a point `clearance` inspects; distances beyond it are reported as CLEARANCE_CAP.
CLEARANCE_REACH = 2
CLEARANCE_CAP = float(CLEARANCE_REACH)


def signed_distance_field(occupancy: np.ndarray) -> np.ndarray:
    """SDF sampled at cell centres, in metres: > 0 in free space, < 0 inside obstacles.

    Distances are measured to the boundary between free and occupied squares (centre-to-centre EDT
    minus half a cell), so a free cell next to an obstacle has +0.5 and a lone obstacle cell -0.5.
    The border outside the map counts as obstacle.
    """
    occ = np.pad(occupancy.astype(bool), 1, constant_values=True)
    outside = distance_transform_edt(~occ)  # free cells: distance to nearest obstacle centre
    inside = distance_transform_edt(occ)  # obstacle cells: distance to nearest free centre
    sdf = np.where(occ, -(inside - 0.5), outside - 0.5)
    return sdf[1:-1, 1:-1].astype(np.float32)


def bilinear(field: np.ndarray, pts: np.ndarray, index: np.ndarray | None = None,
             with_grad: bool = False):
    """Bilinear lookup of a cell-centred field at positions `pts` (..., 2) = (x, y).

    `field` is (H, W), or (B, H, W) with `index` (...) choosing the map of each point. Points outside are
    clamped to the border samples. Returns values (...) and, with `with_grad`, the gradient (..., 2) in
    (d/dx, d/dy), exact for the bilinear interpolant.
    """
    if field.ndim == 2:
        field = field[None]
        index = np.zeros(pts.shape[:-1], dtype=np.int64)
    B, H, W = field.shape
    gx = np.clip(pts[..., 0] - 0.5, 0.0, W - 1.000001)
    gy = np.clip(pts[..., 1] - 0.5, 0.0, H - 1.000001)
    c0 = gx.astype(np.int64)
    r0 = gy.astype(np.int64)
    fx = gx - c0
    fy = gy - r0
    flat = field.reshape(-1)
    base = index * (H * W) + r0 * W + c0
    v00 = flat[base]
    v01 = flat[base + 1]
    v10 = flat[base + W]
    v11 = flat[base + W + 1]
    top = v00 + (v01 - v00) * fx
    bot = v10 + (v11 - v10) * fx
    val = top + (bot - top) * fy
    if not with_grad:
        return val
    dx = (v01 - v00) * (1 - fy) + (v11 - v10) * fy
    dy = bot - top
    return val, np.stack([dx, dy], axis=-1)


def pad_for_clearance(occupancy: np.ndarray) -> np.ndarray:
    """Occupancy padded with obstacle cells so `clearance` can index around any point on the map."""
    return np.pad(occupancy.astype(bool), CLEARANCE_REACH + 1, constant_values=True)


_OFFSETS = np.arange(-CLEARANCE_REACH, CLEARANCE_REACH + 1)


def clearance(padded: np.ndarray, pts: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
    """Exact Euclidean distance from each point to the nearest occupied unit square, capped at CLEARANCE_CAP.

    This is the metric's definition of obstacle distance (ARCHITECTURE.md): outside the map is occupied,
    so a point off the map has clearance 0. `padded` comes from `pad_for_clearance` (H+2p, W+2p), or is a
    stack (B, H+2p, W+2p) with `index` choosing the map of each point.
    """
    if padded.ndim == 2:
        padded = padded[None]
        index = np.zeros(pts.shape[:-1], dtype=np.int64)
    B, Hp, Wp = padded.shape
    p = CLEARANCE_REACH + 1
    H, W = Hp - 2 * p, Wp - 2 * p
    x = pts[..., 0]
    y = pts[..., 1]
    inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
    c0 = np.clip(np.floor(x), -1, W).astype(np.int64)
    r0 = np.clip(np.floor(y), -1, H).astype(np.int64)
    cells = (r0[..., None, None] + _OFFSETS[:, None]) , (c0[..., None, None] + _OFFSETS[None, :])
    rr, cc = cells  # (..., K, K)
    occ = padded.reshape(-1)[(index[..., None, None] * Hp + rr + p) * Wp + cc + p]
    dx = np.maximum(np.maximum(cc - x[..., None, None], 0.0), x[..., None, None] - (cc + 1))
    dy = np.maximum(np.maximum(rr - y[..., None, None], 0.0), y[..., None, None] - (rr + 1))
    d = np.where(occ, np.hypot(dx, dy), CLEARANCE_CAP)
    d = d.reshape(d.shape[:-2] + (-1,)).min(axis=-1)
    return np.where(inside, np.minimum(d, CLEARANCE_CAP), 0.0)


def line_of_sight(sdf: np.ndarray, a: np.ndarray, b: np.ndarray, min_clearance: float,
                  spacing: float = 0.25, index: np.ndarray | None = None) -> np.ndarray:
    """True where the segment a -> b keeps at least `min_clearance` (bilinear SDF) along its length.

    a, b: (..., 2). Segments are sampled every `spacing` metres; all segments are checked in one array
    program (the number of samples is set by the longest segment).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    length = np.linalg.norm(b - a, axis=-1)
    n = int(np.ceil(length.max(initial=0.0) / spacing)) + 1
    s = np.linspace(0.0, 1.0, max(n, 2))
    pts = a[..., None, :] + (b - a)[..., None, :] * s[:, None]
    idx = None if index is None else np.broadcast_to(index[..., None], pts.shape[:-1])
    vals = bilinear(sdf, pts, idx)
    return (vals >= min_clearance).all(axis=-1)


def inflate_free(occupancy: np.ndarray, radius_cells: int = 1) -> np.ndarray:
    """Cells whose (2r+1) x (2r+1) neighbourhood is free.

    With r = 1 the nearest occupied square is at least one full cell away, so the centre has clearance
    >= sqrt(2) > d_obs_min = 1: these are the cells the expert plans on and tasks are placed on.
    """
    occ = np.pad(occupancy.astype(bool), radius_cells, constant_values=True)
    H, W = occupancy.shape
    blocked = np.zeros((H, W), dtype=bool)
    k = 2 * radius_cells + 1
    for dr in range(k):
        for dc in range(k):
            blocked |= occ[dr:dr + H, dc:dc + W]
    return ~blocked
