"""Procedural map families and the deterministic train / eval splits.

`blocks` reproduces the paper's map source (expert.md, "Map source"): m = (uniform noise > a), then a
morphological opening of m with a k x k square (erosion treating the border as set, then dilation); the
opened m is the obstacle layer. Only k x k windows free of noise seeds survive, so obstacles are square-ish
blocks at least k cells wide. The other families add layouts the paper's set lacks: `rooms` (walls with
doors), `maze` (wide corridors with loops) and `forest` (round trees plus U-shaped bug traps, the classic
local minimum of potential-field planners).

Every map is a pure function of (seed, split, index): the same config always yields the same maps, and
train and eval draw from separate random streams.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import binary_dilation, binary_erosion, label

from .geometry import inflate_free
from .grid import GridMap

# Three disjoint random streams: train (learning), val (choosing checkpoints and recipes), eval (reporting).
# A model must never be selected on the maps it is reported on, so validation has a split of its own.
SPLITS = {"train": 1, "eval": 2, "val": 3}
# (k, a_low, a_high) of the paper's map source
BLOCK_RECIPES = ((7, 0.06, 0.09), (5, 0.10, 0.14), (3, 0.35, 0.40))


@dataclass
class MapConfig:
    canvas: int = 140  # every map is planned on a canvas x canvas grid (paper: 140)
    size: int = 100  # side of a generated map before padding into the canvas (paper: 100)
    families: dict[str, float] = field(default_factory=lambda: {"blocks": 1.0})  # family -> weight
    seed: int = 0
    train_maps: int = 5000
    eval_maps: int = 1000
    val_maps: int = 500
    min_open_extent: float = 60.0  # a generated map's largest safe region must span at least this (m)
    max_scale_up: int = 4  # external maps: largest integer up-scaling of a small grid


def blocks(rng: np.random.Generator, size: int) -> np.ndarray:
    k, lo, hi = BLOCK_RECIPES[rng.integers(len(BLOCK_RECIPES))]
    a = rng.uniform(lo, hi)
    m = rng.random((size, size)) > a
    se = np.ones((k, k), dtype=bool)
    eroded = binary_erosion(m, structure=se, border_value=1)
    return binary_dilation(eroded, structure=se, border_value=0)


def rooms(rng: np.random.Generator, size: int) -> np.ndarray:
    occ = np.zeros((size, size), dtype=bool)
    room = int(rng.integers(16, 28))
    wall = int(rng.integers(1, 3))
    for pos in range(room, size - wall, room):  # vertical and horizontal walls
        occ[:, pos:pos + wall] = True
        occ[pos:pos + wall, :] = True
    # a door of 4..7 cells in every wall segment between two crossings
    lines = list(range(room, size - wall, room))
    edges = [0] + lines + [size]
    for pos in lines:
        for a, b in zip(edges[:-1], edges[1:]):
            lo, hi = a + (wall if a else 0) + 1, b - 1
            width = int(rng.integers(4, 8))
            if hi - lo <= width:
                continue
            s = int(rng.integers(lo, hi - width))
            occ[s:s + width, pos:pos + wall] = False
            s = int(rng.integers(lo, hi - width))
            occ[pos:pos + wall, s:s + width] = False
    # clutter: a few boxes inside rooms
    for _ in range(int(rng.integers(4, 14))):
        h, w = rng.integers(2, 6, size=2)
        r, c = rng.integers(0, size - 6, size=2)
        occ[r:r + h, c:c + w] = True
    return occ


def maze(rng: np.random.Generator, size: int) -> np.ndarray:
    cell = int(rng.integers(10, 15))  # corridor pitch
    wall = int(rng.integers(2, 4))
    n = max(2, size // cell)
    occ = np.ones((size, size), dtype=bool)

    def carve(r0, c0, r1, c1):
        occ[r0:r1, c0:c1] = False

    # depth-first maze on an n x n lattice of rooms, then knock out extra walls for loops
    seen = np.zeros((n, n), dtype=bool)
    stack = [(int(rng.integers(n)), int(rng.integers(n)))]
    seen[stack[0]] = True
    links = []
    while stack:
        i, j = stack[-1]
        nbrs = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))
                if 0 <= i + di < n and 0 <= j + dj < n and not seen[i + di, j + dj]]
        if not nbrs:
            stack.pop()
            continue
        ni, nj = nbrs[rng.integers(len(nbrs))]
        seen[ni, nj] = True
        links.append(((i, j), (ni, nj)))
        stack.append((ni, nj))
    for _ in range(int(n * n * 0.25)):
        i, j = rng.integers(n, size=2)
        di, dj = ((1, 0), (0, 1))[rng.integers(2)]
        if i + di < n and j + dj < n:
            links.append(((i, j), (i + di, j + dj)))
    for i in range(n):
        for j in range(n):
            carve(i * cell + wall, j * cell + wall, (i + 1) * cell, (j + 1) * cell)
    for (i, j), (k, l) in links:
        r0, r1 = min(i, k) * cell + wall, (max(i, k) + 1) * cell
        c0, c1 = min(j, l) * cell + wall, (max(j, l) + 1) * cell
        carve(r0, c0, r1, c1)
    return occ


def forest(rng: np.random.Generator, size: int) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    occ = np.zeros((size, size), dtype=bool)
    for _ in range(int(rng.integers(25, 70))):
        cx, cy = rng.uniform(0, size, 2)
        rad = rng.uniform(1.0, 3.5)
        occ |= (xx - cx) ** 2 + (yy - cy) ** 2 <= rad ** 2
    for _ in range(int(rng.integers(2, 5))):  # bug traps: three sides of a box
        h, w = rng.integers(10, 22, size=2)
        r, c = rng.integers(2, size - 24, size=2)
        t = int(rng.integers(2, 4))
        side = rng.integers(4)
        box = np.zeros((size, size), dtype=bool)
        box[r:r + h, c:c + w] = True
        box[r + t:r + h - t, c + t:c + w - t] = False
        if side == 0:
            box[r:r + t, c + t:c + w - t] = False
        elif side == 1:
            box[r + h - t:r + h, c + t:c + w - t] = False
        elif side == 2:
            box[r + t:r + h - t, c:c + t] = False
        else:
            box[r + t:r + h - t, c + w - t:c + w] = False
        occ |= box
    return occ


FAMILIES = {"blocks": blocks, "rooms": rooms, "maze": maze, "forest": forest}


def place_on_canvas(occ: np.ndarray, canvas: int) -> np.ndarray:
    """Centre `occ` on a canvas x canvas grid padded with obstacle."""
    H, W = occ.shape
    if H > canvas or W > canvas:
        raise ValueError(f"a {H} x {W} map does not fit the {canvas} x {canvas} canvas")
    out = np.ones((canvas, canvas), dtype=np.uint8)
    r0, c0 = (canvas - H) // 2, (canvas - W) // 2
    out[r0:r0 + H, c0:c0 + W] = occ
    return out


def largest_safe_extent(occupancy: np.ndarray) -> float:
    """Bounding-box diagonal (m) of the largest 8-connected region of safe cells."""
    lab, n = label(inflate_free(occupancy, 1), structure=np.ones((3, 3)))
    if n == 0:
        return 0.0
    biggest = np.argmax(np.bincount(lab.ravel())[1:]) + 1
    rr, cc = np.nonzero(lab == biggest)
    return float(np.hypot(rr.max() - rr.min(), cc.max() - cc.min()))


def generate_map(cfg: MapConfig, split: str, index: int) -> GridMap:
    """Map `index` of `split` ("train", "val" or "eval"): deterministic in (cfg.seed, split, index)."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; use one of {sorted(SPLITS)}")
    names = sorted(cfg.families)
    unknown = [n for n in names if n not in FAMILIES]
    if unknown:
        raise ValueError(f"map.families: unknown family {unknown}; available: {sorted(FAMILIES)}")
    weights = np.array([cfg.families[n] for n in names], dtype=float)
    if weights.sum() <= 0:
        raise ValueError("map.families: weights must sum to a positive number")
    rng = np.random.default_rng([cfg.seed, SPLITS[split], index])
    family = names[rng.choice(len(names), p=weights / weights.sum())]
    for attempt in range(50):
        occ = place_on_canvas(FAMILIES[family](rng, cfg.size).astype(np.uint8), cfg.canvas)
        if largest_safe_extent(occ) >= cfg.min_open_extent:
            break
    return GridMap(map_id=f"{split}-{index:06d}", occupancy=occ, source=f"generated:{family}",
                   meta={"family": family, "split": split, "index": index, "attempt": attempt})


def split_size(cfg: MapConfig, split: str) -> int:
    return {"train": cfg.train_maps, "val": cfg.val_maps, "eval": cfg.eval_maps}[split]
