"""Training samples as PyTorch Dataset + collate, and as a Ray Data batch function; both share make_sample.

    bank = EpisodeBank.from_folder("data/train")
    loader = DataLoader(ChunkDataset(bank, SampleConfig()), batch_size=128, collate_fn=collate, num_workers=4)

    ds = roken.ray_pool.read_ray_dataset("data/train", "episodes")
    ds.map_batches(EpisodeBatchToSamples("data/train", SampleConfig()), batch_format="numpy")

Randomness is a pure function of (seed, epoch, index) in the Dataset and of (seed, epoch, episode_id) for Ray
batches, so a sample is the same whichever worker or batch makes it.
"""
from __future__ import annotations

import zlib

import numpy as np
import torch

from . import shards
from .samples import SAMPLE_KEYS, EpisodeBank, MapStore, SampleConfig, check, make_sample, sample_shapes


class ChunkDataset(torch.utils.data.Dataset):
    """Map-style dataset: index k draws an episode (uniformly in turn, or by samples.team_size_weights) and
    cuts a random sample from it. `samples_per_epoch` defaults to one per episode."""

    def __init__(self, bank: EpisodeBank, cfg: SampleConfig, seed: int = 0, samples_per_epoch: int | None = None):
        check(cfg)
        self.bank, self.cfg, self.seed = bank, cfg, seed
        self.length = samples_per_epoch or len(bank)
        self.epoch = 0
        weights = bank.episode_weights(cfg.team_size_weights)
        self.cdf = None if weights is None else np.cumsum(weights)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, k: int) -> dict[str, np.ndarray]:
        rng = np.random.default_rng([self.seed, self.epoch, k])
        if self.cdf is None:
            i = k % len(self.bank)
        else:
            i = min(int(np.searchsorted(self.cdf, rng.random() * self.cdf[-1], side="right")), len(self.bank) - 1)
        return make_sample(self.bank, i, rng, self.cfg)


def stack(samples: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([s[k] for s in samples]) for k in SAMPLE_KEYS}


def empty_batch(cfg: SampleConfig) -> dict[str, np.ndarray]:
    """A batch of no samples with the right per-sample shapes (a Ray batch whose episodes all failed)."""
    return {k: np.zeros((0, *shape), dtype) for k, (shape, dtype) in sample_shapes(cfg).items()}


def collate(samples: list[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    """DataLoader collate_fn: a dict of batched tensors (robot_mask bool, num_robots int64, the rest float32)."""
    return {k: torch.from_numpy(v) for k, v in stack(samples).items()}


def to_device(batch: dict, device: torch.device | str) -> dict[str, torch.Tensor]:
    """Numpy or tensor batch (from collate or Ray's iter_torch_batches) onto a device."""
    return {k: torch.as_tensor(v).to(device, non_blocking=True) for k, v in batch.items()}


class EpisodeBatchToSamples:
    """Ray Data `map_batches` callable: a numpy batch of episode rows -> a batch of training samples.

    The maps of `location` are read and decoded once per worker, and their SDFs kept across batches (maps are
    small next to episodes). Each episode row
    gives `samples_per_episode` samples; rows whose `success` is false are dropped unless successful_only is
    off. Usable without Ray on any dict of episode columns."""

    def __init__(self, location: str, cfg: SampleConfig, seed: int = 0, epoch: int = 0, samples_per_episode: int = 1,
                 successful_only: bool = True):
        check(cfg)
        self.successful_only = successful_only
        self.location, self.cfg, self.seed, self.epoch = location, cfg, seed, epoch
        self.samples_per_episode = samples_per_episode
        self._maps: MapStore | None = None

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if self._maps is None:
            self._maps = MapStore(shards.read_table(self.location, "maps"), self.cfg.canvas)
        if self.successful_only and "success" in batch:
            keep = np.asarray(batch["success"], dtype=bool)
            batch = {k: np.asarray(v)[keep] for k, v in batch.items()}
        if len(batch["episode_id"]) == 0:
            return empty_batch(self.cfg)
        bank = EpisodeBank.from_columns(batch, self._maps)
        out = []
        for i in range(len(bank)):
            key = zlib.crc32(bank.episode_ids[i].encode())
            for j in range(self.samples_per_episode):
                out.append(make_sample(bank, i, np.random.default_rng([self.seed, self.epoch, key, j]), self.cfg))
        return stack(out)
