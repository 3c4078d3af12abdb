"""GRPO prompts (paper appendix, "Rollout dataset collection"): an expert episode and a time t with at least
`min_future` steps left; the state at t must satisfy the task's constraints (clearance, spacing, connected),
so RL starts from feasible team configurations. A prompt is (episode, t); its condition - map, positions at t,
leader, the episode's goal - comes from the shared condition builder, so a rollout worker and the learner
rebuild exactly the same model inputs from two integers.
"""
from __future__ import annotations

import numpy as np

from ..data.condition import build_condition
from ..data.samples import EpisodeBank, SampleConfig
from ..world.geometry import clearance, pad_for_clearance
from ..world.graph import connected
from ..world.tasks import TaskConfig


def state(bank: EpisodeBank, prompt: tuple[int, int]) -> tuple[np.ndarray, int, np.ndarray, int]:
    """(positions (n, 2), leader, goal (2,), map index) of prompt (episode, t)."""
    i, t = prompt
    return (bank.positions(i)[t].astype(np.float64), int(bank.leader[i]), bank.goal[i].astype(np.float64),
            int(bank.map_index[i]))


def condition(bank: EpisodeBank, prompt: tuple[int, int], cfg: SampleConfig) -> dict[str, np.ndarray]:
    """The model's inputs for a prompt, with one token per robot of the team."""
    pos, leader, goal, m = state(bank, prompt)
    return build_condition(bank.occupancy[m], pos, leader, goal, cfg, tokens=len(pos))


def feasible(occupancy_padded: np.ndarray, positions: np.ndarray, tc: TaskConfig) -> bool:
    p = np.asarray(positions, np.float64)
    if (clearance(occupancy_padded, p) < tc.d_obs_min).any():
        return False
    if len(p) < 2:
        return True
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    if (d[~np.eye(len(p), dtype=bool)] < tc.d_coll_min).any():
        return False
    return bool(connected(d[None], tc.comm_radius)[0])


class PromptSource:
    """Fresh prompts drawn uniformly over the eligible episodes (team sizes, enough steps) and their times."""

    def __init__(self, bank: EpisodeBank, tc: TaskConfig, min_future: int, team_sizes: list[int] | None = None,
                 max_robots: int | None = None):
        self.bank, self.tc, self.min_future = bank, tc, min_future
        ok = bank.num_steps >= min_future
        if team_sizes:
            ok &= np.isin(bank.num_robots, team_sizes)
        if max_robots is not None:
            ok &= bank.num_robots <= max_robots
        self.eligible = np.flatnonzero(ok)
        if len(self.eligible) == 0:
            raise ValueError(f"no episode to draw prompts from: each needs >= rl.min_future={min_future} steps"
                             f"{f', a team size in rl.team_sizes={team_sizes}' if team_sizes else ''}"
                             f"{f' and at most {max_robots} robots' if max_robots else ''}; lower rl.min_future or "
                             f"use a dataset with longer episodes (team sizes present: "
                             f"{sorted(set(bank.num_robots.tolist()))}, longest {int(bank.num_steps.max())} steps)")
        self._padded: dict[int, np.ndarray] = {}

    def draw(self, rng: np.random.Generator, count: int, tries: int = 20) -> list[tuple[int, int]]:
        out = []
        while len(out) < count:
            i = int(self.eligible[rng.integers(len(self.eligible))])
            for _ in range(tries):
                t = int(rng.integers(0, int(self.bank.num_steps[i]) - self.min_future + 1))
                pos, _, _, m = state(self.bank, (i, t))
                if m not in self._padded:
                    self._padded[m] = pad_for_clearance(self.bank.occupancy[m])
                if feasible(self._padded[m], pos, self.tc):
                    out.append((i, t))
                    break
        return out
