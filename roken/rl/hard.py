"""Hard prompts (paper appendix: "we optionally mix in hard prompts ... selected from mid-states where the
pretrained policy previously generated invalid or low-quality candidates").

The store is a torchrl `ReplayBuffer` over a `LazyTensorStorage` of prompt TensorDicts {episode, t, difficulty}
with `DifficultySampler`, which draws prompt i with probability proportional to difficulty_i ** (1 / T).
A prompt's difficulty comes from its last group (`difficulty`), floored so an easy prompt is still drawn now
and then.
torchrl 0.14's own `PrioritizedSampler` needs its compiled extension, which does not load with torch 2.13
("SumSegmentTreeFp32 is not available"); this sampler is plain torch (a multinomial over the stored
difficulties), which at the store's few thousand entries costs microseconds.
"""
from __future__ import annotations

import logging
import os

import numpy as np
import torch

# torchrl imports Ray, which reads its auth mode once: token authentication stays on (as in roken.ray_pool)
os.environ.setdefault("RAY_AUTH_MODE", "token")

from tensordict import TensorDict  # noqa: E402
from torchrl.data import LazyTensorStorage, ReplayBuffer  # noqa: E402
from torchrl.data.replay_buffers.samplers import Sampler  # noqa: E402

FLOOR = 0.02  # the lowest difficulty a stored prompt keeps


class DifficultySampler(Sampler):
    """Samples storage indices with probability ~ difficulty ** (1 / temperature) (with replacement)."""

    def __init__(self, temperature: float = 1.0, key: str = "difficulty"):
        super().__init__()
        self.temperature, self.key = temperature, key

    def sample(self, storage, batch_size: int):
        n = len(storage)
        if n == 0:
            raise RuntimeError("the hard-prompt store is empty")
        d = storage[torch.arange(n)][self.key].float().clamp(min=FLOOR)
        w = d ** (1.0 / self.temperature)
        index = torch.multinomial(w, batch_size, replacement=True, generator=self._rng)
        return index, {}

    def _empty(self):
        pass

    def dumps(self, path):
        pass

    def loads(self, path):
        pass

    def state_dict(self) -> dict:
        return {"temperature": self.temperature}

    def load_state_dict(self, state_dict: dict) -> None:
        self.temperature = state_dict.get("temperature", self.temperature)


def difficulty(hard: np.ndarray, reward: np.ndarray) -> float:
    """A group's difficulty in [0, 1]: half the share of candidates with a hard violation plus half the share
    of low-quality ones (reward more than 1 below the group's best, i.e. 20 cost units at s = 20)."""
    fail = float(np.mean(hard))
    low = float(np.mean(reward < reward.max() - 1.0)) if len(reward) else 0.0
    return 0.5 * fail + 0.5 * low


class HardPrompts:
    """The prompt store: `add` a group's prompt with its difficulty; `draw` prompts weighted by difficulty."""

    def __init__(self, size: int, temperature: float = 1.0, seed: int = 0):
        logging.getLogger("torchrl").setLevel(logging.WARNING)  # not a line per storage it initialises
        self.gen = torch.Generator().manual_seed(seed)
        self.rb = ReplayBuffer(storage=LazyTensorStorage(size), sampler=DifficultySampler(temperature),
                               generator=self.gen)

    def __len__(self) -> int:
        return len(self.rb)

    def add(self, prompts: list[tuple[int, int]], difficulties: list[float]) -> None:
        if not prompts:
            return
        p = torch.as_tensor(prompts, dtype=torch.long).reshape(-1, 2)
        self.rb.extend(TensorDict({"episode": p[:, 0], "t": p[:, 1],
                                   "difficulty": torch.as_tensor(difficulties, dtype=torch.float32)},
                                  batch_size=[len(p)]))

    def draw(self, count: int) -> list[tuple[int, int]]:
        if count <= 0 or len(self) == 0:
            return []
        td = self.rb.sample(batch_size=count)
        return list(zip(td["episode"].tolist(), td["t"].tolist()))

    def state_dict(self) -> dict:
        n = len(self)
        td = self.rb.storage[torch.arange(n)] if n else None
        return {"generator": self.gen.get_state(),
                "episode": td["episode"] if n else torch.zeros(0, dtype=torch.long),
                "t": td["t"] if n else torch.zeros(0, dtype=torch.long),
                "difficulty": td["difficulty"] if n else torch.zeros(0)}

    def load_state_dict(self, s: dict) -> None:
        self.gen.set_state(s["generator"])
        if len(s["episode"]):
            self.add(list(zip(s["episode"].tolist(), s["t"].tolist())), s["difficulty"].tolist())
