"""DART's disturbances of the expert (Laskey et al. 2017, "DART: Noise Injection for Robust Imitation Learning").

A learner's plans leave the expert's course; imitation data shows only the course. DART pushes the expert itself
off course while it records, and keeps its answer as the label. Here, once per episode (expert.disturb > 0), at a
step drawn from the task's seed in the first 80 % of its nominal duration, for `disturb_steps` steps:
  random    every robot's command gets a constant offset ~ N(0, disturb^2 I) m/step;
  approach  one robot (drawn from the seed) walks at `disturb` m/step toward its nearest team-mate, which holds
            (both commands replaced: the expert's own repulsion would cancel an added push) - the pair closing
            in that ends most plain-Roken episodes (README "DART").
The push goes in before the expert's safety filter, so the episode stays feasible; the expert then recovers
with its hidden state (inertia, tree, reference progress) intact.
"""
from __future__ import annotations

import numpy as np

MODES = ("random", "approach")


def check(disturb: float, steps: int, mode: str) -> None:
    """Refuse a push the expert cannot make, naming the settings (the expert and the dataset check call it)."""
    if disturb < 0 or steps < 1 or mode not in MODES:
        raise ValueError(f"expert.disturb={disturb} / disturb_steps={steps} / disturb_mode={mode!r}: the push (m/step) "
                         f"must be >= 0 (0 = off), last >= 1 step, and be one of {', '.join(MODES)}")


def draw(seed: int, length: float, max_step: float, n: int, disturb: float) -> tuple[int, np.ndarray, int]:
    """(first step of the push, each robot's offset (n, 2) for `random`, the robot that walks for `approach`);
    length: the leader's reference path (m), so the push comes in the first 80 % of length / max_step steps."""
    rng = np.random.default_rng([seed, 0xDA27])
    at = int(rng.integers(0, max(1, int(0.8 * length / max_step))))
    return at, rng.normal(0.0, disturb, (n, 2)), int(rng.integers(n))


def push(q: np.ndarray, offsets: np.ndarray, who: np.ndarray, mode: str, disturb: float):
    """For teams q (S, N, 2): the command offsets (S, N, 2) and the robots whose own command they replace (S, N)."""
    held = np.zeros(q.shape[:2], bool)
    if mode == "random":
        return offsets, held
    sl = np.arange(len(q))
    d = np.linalg.norm(q - q[sl, who][:, None], axis=-1)
    d[sl, who] = np.inf
    mate = d.argmin(1)
    to = q[sl, mate] - q[sl, who]  # (S, 2)
    off = np.zeros_like(q)
    off[sl, who] = disturb * to / np.maximum(np.linalg.norm(to, axis=-1, keepdims=True), 1e-9)
    held[sl, who] = held[sl, mate] = q.shape[1] > 1  # a lone robot has no mate to walk at
    return off, held
