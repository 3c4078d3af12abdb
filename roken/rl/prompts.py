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
from ..world.grid import GridMap
from ..world.tasks import TaskConfig, check_start


def state(bank: EpisodeBank, prompt: tuple[int, int]) -> tuple[np.ndarray, int, np.ndarray, int]:
    """(positions (n, 2), leader, goal (2,), map index) of prompt (episode, t)."""
    i, t = prompt
    return (bank.positions(i)[t].astype(np.float64), int(bank.leader[i]), bank.goal[i].astype(np.float64),
            int(bank.map_index[i]))


def condition(bank: EpisodeBank, prompt: tuple[int, int], cfg: SampleConfig) -> dict[str, np.ndarray]:
    """The model's inputs for a prompt, with one token per robot of the team."""
    pos, leader, goal, m = state(bank, prompt)
    before = bank.positions(prompt[0])[max(0, prompt[1] - cfg.interval)]  # one chunk move earlier
    return build_condition(bank.occupancy[m], pos, leader, goal, cfg, tokens=len(pos), previous=before)


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
        self._maps: dict[int, GridMap] = {}

    def draw(self, rng: np.random.Generator, count: int, tries: int = 20) -> list[tuple[int, int]]:
        out = []
        while len(out) < count:
            i = int(self.eligible[rng.integers(len(self.eligible))])
            for _ in range(tries):
                t = int(rng.integers(0, int(self.bank.num_steps[i]) - self.min_future + 1))
                pos, _, _, m = state(self.bank, (i, t))
                if m not in self._maps:
                    self._maps[m] = GridMap(self.bank.map_ids[m], self.bank.occupancy[m])
                if check_start(self._maps[m], pos, self.tc) is None:  # the task's own start constraints
                    out.append((i, t))
                    break
        return out
