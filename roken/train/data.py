"""Training data for the loop: a step-indexed sample stream, the held-out split, and the dataset fingerprint.

The sample at global index g is a pure function of (seed, g): g = epoch * len(bank) + position, each epoch
visits the episodes in its own random order, and the sample's randomness comes from (seed, epoch, position).
Step s of a run with global batch B uses indices s * B .. (s + 1) * B - 1, and rank r of W takes the r-th
slice of B / W. So a run draws the same global batches whatever its number of workers, and resuming at step s
needs nothing but s (no data-loader state to save).
"""
from __future__ import annotations

import json
import zlib
from functools import lru_cache

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import torch

from ..data import fs, shards
from ..data.loader import collate
from ..data.samples import WINDOW_COLUMNS, EpisodeBank, MapStore, SampleConfig, check, episode_columns, make_sample


class SampleStream(torch.utils.data.Dataset):
    """Global sample index -> training sample (see the module docstring)."""

    def __init__(self, bank: EpisodeBank, cfg: SampleConfig, seed: int = 0, source_weights: np.ndarray | None = None):
        check(cfg)
        self.bank, self.cfg, self.seed = bank, cfg, seed
        weights = bank.episode_weights(cfg.team_size_weights)
        if source_weights is not None:  # a mix of datasets (DAgger): each its share, team sizes as configured
            weights = source_weights if weights is None else weights * source_weights
        self.cdf = None if weights is None else np.cumsum(weights)
        self._order = lru_cache(maxsize=2)(self._epoch_order)

    def _epoch_order(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch, 0x5EED]).permutation(len(self.bank))

    def __len__(self) -> int:  # nominal: indices are unbounded, one epoch is one pass over the episodes
        return len(self.bank)

    def __getitem__(self, g: int) -> dict[str, np.ndarray]:
        epoch, pos = divmod(int(g), len(self.bank))
        rng = np.random.default_rng([self.seed, epoch, pos])
        if self.cdf is None:
            i = int(self._order(epoch)[pos])
        else:
            i = min(int(np.searchsorted(self.cdf, rng.random() * self.cdf[-1], side="right")), len(self.bank) - 1)
        return make_sample(self.bank, i, rng, self.cfg)


class StepIndices(torch.utils.data.Sampler):
    """The global indices rank `rank` of `world` draws for steps start..stop-1 (global batch `batch`)."""

    def __init__(self, start: int, stop: int, batch: int, rank: int = 0, world: int = 1):
        if batch % world:
            raise ValueError(f"train.batch_size={batch} is not divisible by the {world} workers; "
                             f"choose a multiple of the worker count")
        self.start, self.stop, self.batch, self.rank, self.local = start, stop, batch, rank, batch // world

    def __len__(self) -> int:
        return max(self.stop - self.start, 0) * self.local

    def __iter__(self):
        for s in range(self.start, self.stop):
            base = s * self.batch + self.rank * self.local
            yield from range(base, base + self.local)


def make_loader(stream: SampleStream, start: int, stop: int, batch: int, rank: int, world: int, workers: int,
                pin: bool = False) -> torch.utils.data.DataLoader:
    sampler = StepIndices(start, stop, batch, rank, world)
    # Its own generator: the DataLoader draws a base seed when iterated, which must not consume the global
    # RNG that the diffusion noise comes from (a resumed run would otherwise draw other noise).
    gen = torch.Generator().manual_seed(start * 7919 + rank)
    return torch.utils.data.DataLoader(
        stream, batch_size=sampler.local, sampler=sampler, collate_fn=collate, num_workers=workers,
        pin_memory=pin, persistent_workers=False, generator=gen, prefetch_factor=4 if workers > 0 else None,
        worker_init_fn=_worker_init if workers > 0 else None)


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)  # sample making is numpy; keep loader processes off the trainer's cores


def _held_out(map_ids: pa.Array, fraction: float, seed: int) -> np.ndarray:
    """True for episodes on held-out maps: a hash of (seed, map_id) below `fraction` (stable across runs)."""
    h = np.array([zlib.crc32(f"{seed}:{m}".encode()) for m in map_ids.to_pylist()], dtype=np.float64)
    return h / 2 ** 32 < fraction


def load_banks(data: str | list[str], canvas: int, val_data: str | None = None, val_fraction: float = 0.0,
               seed: int = 0, shares: list[float] | None = None
               ) -> tuple[EpisodeBank, EpisodeBank | None, np.ndarray | None]:
    """The training bank of `data` and the validation bank: `val_data` (a `val`-split dataset), else the
    episodes of a `val_fraction` of `data`'s maps (never trained on), else None. Successful episodes only.

    `data` may be several datasets (DAgger: the expert dataset and the relabelled rounds); `shares` then gives
    each one's share of the training samples (default: in proportion to their episodes), returned as per-episode
    sampling weights (None for one dataset)."""
    locations = [data] if isinstance(data, str) else list(data)
    if shares is not None and len(shares) != len(locations):
        raise ValueError(f"{len(shares)} data shares for {len(locations)} datasets")
    tables, map_tables, sizes = [], [], []
    for loc in locations:
        tab, maps = _read(loc)
        tables.append(tab)
        map_tables.append(maps)
        sizes.append(tab.num_rows)
    train_tab = pa.concat_tables(tables) if len(tables) > 1 else tables[0]
    source = np.repeat(np.arange(len(locations)), sizes)
    store = MapStore(_unique_maps(map_tables), canvas)
    val = None
    if val_data:
        val_tab, val_maps = _read(val_data)
        val = EpisodeBank.from_arrow(val_tab, MapStore(val_maps, canvas))
    elif val_fraction > 0:
        held = _held_out(train_tab.column("map_id").combine_chunks(), val_fraction, seed)
        if held.all() or not held.any():
            raise ValueError(f"{locations[0]}: train.val_fraction={val_fraction} holds out {int(held.sum())} of "
                             f"{len(held)} episodes' maps; use a dataset with more maps or pass --val-data")
        val = EpisodeBank.from_arrow(train_tab.filter(pa.array(held)), store)
        train_tab, source = train_tab.filter(pa.array(~held)), source[~held]
    weights = None
    if len(locations) > 1:
        counts = np.bincount(source, minlength=len(locations)).astype(np.float64)
        share = np.asarray(shares if shares is not None else counts, dtype=np.float64)
        if (share < 0).any() or share[counts > 0].sum() <= 0:
            raise ValueError(f"data shares {list(share)} must be >= 0 with a positive total")
        weights = share[source] / np.maximum(counts[source], 1)
    return EpisodeBank.from_arrow(train_tab, store), val, weights


def _unique_maps(tables: list[pa.Table]) -> pa.Table:
    """The maps of several datasets, each map id once (DAgger's rounds re-use the expert dataset's maps)."""
    if len(tables) == 1:
        return tables[0]
    both = pa.concat_tables([t.select(tables[0].column_names) for t in tables])
    _, first = np.unique(np.asarray(both.column("map_id").to_pylist(), dtype=object), return_index=True)
    return both.take(pa.array(np.sort(first)))


def _read(location: str) -> tuple[pa.Table, pa.Table]:
    check_dataset(location)
    cols = episode_columns(location)
    episodes = shards.read_table(location, "episodes", columns=cols, successful_only=True)
    for c in WINDOW_COLUMNS:  # 0 = no bound (expert episodes); lets datasets with and without the columns be mixed
        if c not in cols:
            episodes = episodes.append_column(c, pa.array(np.zeros(episodes.num_rows, np.int32)))
    return episodes, shards.read_table(location, "maps")


def check_dataset(location: str, role: str = "--data") -> int:
    """Fail early, naming the folder and the fix, on a dataset that cannot be trained on (before any worker
    starts or anything is written); returns the number of successful episodes. An evaluation folder is never
    training data, and a dataset of `eval` maps is neither training nor validation data: choosing a checkpoint
    on the maps evaluations report on would tune on the test set."""
    if fs.exists(fs.join(location, "metrics.json")) and not fs.exists(fs.join(location, "manifest.json")):
        raise ValueError(f"{role} {location}: this is an evaluation folder (metrics.json, no manifest.json), not a "
                         f"dataset; make one with pipelines/generate.py --maps {'val' if role == '--val-data' else 'train'}")
    try:
        maps = json.loads(fs.read_bytes(fs.join(location, "manifest.json")))["config"]["dataset"]["maps"]
    except (OSError, ValueError, KeyError, TypeError):
        maps = None
    if maps == "eval":
        raise ValueError(f"{role} {location}: this dataset was generated on the `eval` maps, the maps evaluations "
                         f"report on; training or choosing checkpoints there tunes on the test set. Generate "
                         f"{'validation' if role == '--val-data' else 'training'} data with pipelines/generate.py "
                         f"--maps {'val' if role == '--val-data' else 'train'}")
    if not fs.exists(fs.join(location, "episodes")):
        raise ValueError(f"--data {location}: no dataset there (no episodes/ folder); make one with "
                         f"pipelines/generate.py --out {location}")
    success = shards.read_table(location, "episodes", columns=["success"]).column("success")
    n = int(pc.sum(success).as_py() or 0)
    if len(success) == 0:
        raise ValueError(f"--data {location}: the dataset holds no episodes; generate it first")
    if n == 0:
        raise ValueError(f"--data {location}: none of its {len(success)} episodes is successful, so there is "
                         f"nothing to learn from; regenerate it (the expert keeps successful episodes by default)")
    return n


def fingerprint(location: str | list[str]) -> dict:
    """What identifies the training data in a checkpoint: the dataset's manifest fingerprint and size."""
    if not isinstance(location, str):
        return {"datasets": [fingerprint(loc) for loc in location]}
    try:
        m = json.loads(fs.read_bytes(fs.join(location, "manifest.json")))
    except (OSError, ValueError):
        return {"location": str(location), "fingerprint": None}
    return {"location": str(location), "fingerprint": m.get("fingerprint"), "episodes": m.get("episodes"),
            "maps": m.get("maps")}
