"""Closed-loop validation during training: what users judge a model by, measured while it trains.

A fixed set of tasks on the `val` map split (disjoint from `train`, which the model learns from, and from
`eval`, which evaluations report on) is rolled out with the real `RokenRollout` (the planner's defaults: plain
Roken, one candidate, DDIM, re-plan every 2 moves) on the EMA weights, and scored by the harness's metrics:

  closed_loop/success             full success (reach, no collision of either kind, always connected)
  closed_loop/reach               the leader reached its goal
  closed_loop/obstacle_collision  some robot came closer than d_obs_min to an obstacle
  closed_loop/inter_collision     some pair came closer than d_coll_min
  closed_loop/connectivity        the team stayed connected at every step

Task e runs on val map e mod M with the task seed (seed, N, e), as the harness draws them, so every checkpoint
of every run with the same settings is scored on the same episodes; the planner's noise is seeded per task.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch

from ..eval.metrics import summarize
from ..expert.laplacian import ExpertConfig
from ..model.diffusion import NoiseSchedule
from ..data.samples import SampleConfig
from ..plan.planner import RokenPlanner
from ..plan.rollout import PlanConfig, RokenRollout
from ..world.maps import MapConfig, generate_map, split_size
from ..world.metrics import episode_metrics
from ..world.tasks import TaskConfig, TaskError, sample_task

KEYS = ("success", "reach", "obstacle_collision", "inter_collision", "connectivity")


class ClosedLoopValidator:
    def __init__(self, num_tasks: int = 32, robots: int = 4, task: TaskConfig | None = None,
                 plan: PlanConfig | None = None, maps: MapConfig | None = None, seed: int = 0,
                 split: str = "val"):
        self.tc = task or TaskConfig()
        self.pc = replace(plan or PlanConfig(), select="none", candidates=1, record_plans=False)
        mc = maps or MapConfig()
        n_maps = min(split_size(mc, split), num_tasks)
        self.maps = [generate_map(mc, split, i) for i in range(n_maps)]
        self.tasks = []
        for e in range(num_tasks):
            gm = self.maps[e % n_maps]
            try:
                self.tasks.append(sample_task(gm, robots, self.tc, np.random.default_rng([seed, robots, e]), seed=e))
            except TaskError:
                continue  # a map without room for the team: the task set is still fixed by (seed, index)
        self.by_id = {m.map_id: m for m in self.maps}

    @torch.no_grad()
    def evaluate(self, model: torch.nn.Module, schedule: NoiseSchedule, samples: SampleConfig,
                 device: torch.device | str = "cpu") -> dict[str, float]:
        """Roll `model` out on the fixed tasks; returns the closed_loop/* means (and its wall time)."""
        t0 = time.perf_counter()
        was = model.training
        planner = RokenPlanner(model, schedule, samples, device, "fp32", "training EMA")
        rows = []
        for i, pos, _ in RokenRollout(planner, self.pc, self.tc, ExpertConfig()).run(self.tasks, self.by_id):
            t = self.tasks[i]
            rows.append(episode_metrics(pos, self.by_id[t.map_id], np.asarray(t.goal), t.leader, self.tc))
        model.train(was)
        m = summarize(rows)
        out = {f"closed_loop/{k}": m["full_success" if k == "success" else k] for k in KEYS}
        return out | {"closed_loop/episodes": float(len(rows)), "time/closed_loop_s": time.perf_counter() - t0}


def score(validation: dict) -> tuple[float, float] | None:
    """The "best" checkpoint's key: closed-loop success, ties broken by reach (None without closed loop)."""
    if validation.get("closed_loop/success") is None:
        return None
    return float(validation["closed_loop/success"]), float(validation.get("closed_loop/reach", 0.0))


def format_closed_loop(m: dict) -> str:
    return "closed loop (val tasks): " + ", ".join(f"{k} {m[f'closed_loop/{k}']:.3f}" for k in KEYS
                                                    if f"closed_loop/{k}" in m)
