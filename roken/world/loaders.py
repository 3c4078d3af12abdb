"""External maps: MovingAI `.map`, grayscale images (dark = obstacle) and `.npy`, fitted to the canvas.

Fitting (ARCHITECTURE.md): a map larger than the canvas is max-pooled down by the smallest integer factor
that fits (an obstacle cell anywhere in a block blocks the block, so obstacles never vanish); a small grid
is scaled up by the largest integer factor that fits, at most `max_scale_up`, so its corridors become wide
enough for robots that need 1 m clearance; then it is centred on the canvas with obstacle padding.
"""
from __future__ import annotations

import glob
from pathlib import Path

import numpy as np

from .grid import GridMap
from .maps import MapConfig, place_on_canvas

MOVINGAI_FREE = set(".GS")
MOVINGAI_BLOCKED = set("@OTW")
IMAGE_SUFFIXES = {".png", ".pgm", ".bmp", ".jpg", ".jpeg", ".tif", ".tiff"}
MAP_SUFFIXES = {".map", ".npy"} | IMAGE_SUFFIXES


class MapError(ValueError):
    """A map file that cannot be used, with the file and the reason."""

    def __init__(self, path, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path = str(path)
        self.reason = reason


def read_movingai(path: str | Path) -> np.ndarray:
    """A MovingAI .map file as an occupancy grid (h, w), 1 = obstacle ('.', 'G', 'S' free; '@', 'O', 'T', 'W' not)."""
    lines = Path(path).read_text().splitlines()
    header = {}
    i = 0
    while i < len(lines) and lines[i].strip().lower() != "map":
        parts = lines[i].split()
        if len(parts) == 2:
            header[parts[0].lower()] = parts[1]
        i += 1
    if i == len(lines) or "height" not in header or "width" not in header:
        raise MapError(path, "not a MovingAI map: expected 'type', 'height H', 'width W' and 'map' header lines")
    try:
        H, W = int(header["height"]), int(header["width"])
    except ValueError:
        raise MapError(path, "height and width in the header must be integers") from None
    rows = [r.rstrip("\r") for r in lines[i + 1:i + 1 + H]]
    if len(rows) != H or any(len(r) < W for r in rows):
        raise MapError(path, f"the header says {H} x {W} but the grid has {len(rows)} rows of "
                             f"{min((len(r) for r in rows), default=0)}+ characters")
    grid = np.array([list(r[:W]) for r in rows])
    unknown = set(np.unique(grid)) - MOVINGAI_FREE - MOVINGAI_BLOCKED
    if unknown:
        raise MapError(path, f"unknown terrain characters {sorted(unknown)}; free: . G S, blocked: @ O T W")
    return np.isin(grid, list(MOVINGAI_BLOCKED)).astype(np.uint8)


def read_image(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            gray = np.asarray(im.convert("L"), dtype=np.uint8)
    except (UnidentifiedImageError, OSError) as e:
        raise MapError(path, f"unreadable image ({e})") from None
    return (gray < 128).astype(np.uint8)  # dark = obstacle


def read_npy(path: Path) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        # numpy's own message about allow_pickle would suggest turning it on; never: it runs code from the file
        why = "not a valid .npy array file" if "pickle" in str(e) or "magic" in str(e).lower() else str(e)
        raise MapError(path, f"unreadable .npy ({why}); save a 2-D 0/1 array with numpy.save") from None
    if arr.ndim != 2:
        raise MapError(path, f"expected a 2-D occupancy grid, got shape {arr.shape}")
    if arr.dtype != bool:
        if not np.issubdtype(arr.dtype, np.number):
            raise MapError(path, f"expected numbers, got dtype {arr.dtype}")
        vals = np.unique(arr)
        if not np.isin(vals, [0, 1]).all():
            raise MapError(path, f"non-binary values {vals[:6].tolist()}...; use 0 = free, 1 = obstacle")
    return arr.astype(np.uint8)


def fit_to_canvas(occ: np.ndarray, canvas: int, max_scale_up: int) -> tuple[np.ndarray, dict]:
    H, W = occ.shape
    info = {"original_shape": [H, W], "scale": 1.0}
    if max(H, W) > canvas:
        f = int(np.ceil(max(H, W) / canvas))
        Hp, Wp = -(-H // f) * f, -(-W // f) * f
        padded = np.ones((Hp, Wp), dtype=np.uint8)
        padded[:H, :W] = occ
        occ = padded.reshape(Hp // f, f, Wp // f, f).max(axis=(1, 3))
        info["scale"] = 1.0 / f
    else:
        k = max(1, min(max_scale_up, canvas // max(H, W)))
        if k > 1:
            occ = np.kron(occ, np.ones((k, k), dtype=np.uint8))
            info["scale"] = float(k)
    return place_on_canvas(occ, canvas), info


def load_map_file(path: str | Path, cfg: MapConfig) -> GridMap:
    """Read, validate and fit one map file; raises MapError naming the file and the reason."""
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise MapError(path, "no such file")
    if suffix == ".map":
        try:
            raw = read_movingai(path)
        except UnicodeDecodeError:
            raise MapError(path, "not a text file; a MovingAI .map is text") from None
    elif suffix == ".npy":
        raw = read_npy(path)
    elif suffix in IMAGE_SUFFIXES:
        raw = read_image(path)
    else:
        raise MapError(path, f"unknown map format {suffix!r}; use .map, .npy or an image ({sorted(IMAGE_SUFFIXES)})")
    if raw.ndim != 2 or min(raw.shape) < 1:
        raise MapError(path, f"expected a non-empty 2-D grid, got shape {raw.shape}")
    if raw.all():
        raise MapError(path, "every cell is blocked")
    occ, info = fit_to_canvas(raw, cfg.canvas, cfg.max_scale_up)
    gm = GridMap(map_id=path.stem, occupancy=occ, source=str(path), meta=info)
    if not gm.safe_cells.any():
        raise MapError(path, "no free region can hold a robot: no free cell has a free 3 x 3 neighbourhood "
                             "after fitting to the canvas (corridors narrower than 3 cells)")
    return gm


def find_map_files(spec: str) -> list[Path]:
    """Map files named by `spec`: a folder (its map files, sorted), a glob, or one file."""
    p = Path(spec)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in MAP_SUFFIXES)
    elif p.is_file():
        files = [p]
    else:
        files = sorted(Path(f) for f in glob.glob(spec) if Path(f).suffix.lower() in MAP_SUFFIXES)
    if not files:
        raise MapError(spec, "no map files found; pass 'train', 'val', 'eval', a folder, a glob or a file "
                             "of .map / .npy / .png maps")
    return files
