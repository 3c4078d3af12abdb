"""Roken in a robot's loop: the deployable planner, one re-plan at a time, for user code.

    ctl = RokenController.load("models/roken-cpu-four-dagger", "configs/deploy.yaml")
    team = ctl.start(occupancy, positions, leader=0, goal=(120, 35))  # per task: free-space fields built once
    while not team.reached:
        plan = team.replan()        # (n, 16, 2) metres: guided, verified, ranked (team.held: a safety stop)
        ...                         # your robots drive the first ctl.plan.replan_every moves of plan
        team.update(positions)      # where they are now, (n, 2), or every simulator step since, (k, n, 2)
    # in simulation, team.step() drives those moves with the harness's step rule instead of update()

`RokenPlanner.plan` is the paper's planner: one sample, no shield (plain `roken`, 0.02 full success on the
Table-1 tasks with the shipped CPU model). The controller is the row that works (`configs/deploy.yaml`, 0.81):
constraint-guided sampling, G candidates verified on the known map at every executed simulator step, ranked by
free-space progress, the last chosen plan carried as one more candidate, clustered rollout for large teams. It
runs exactly the closed-loop harness's code (`RokenRollout.plan_step` on one episode), so a team driven through it
makes the plans `pipelines/evaluate.py` scores (a test replays an evaluation episode through it).
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ..expert.laplacian import ExpertConfig
from ..world.grid import GridMap
from ..world.tasks import Task, TaskConfig, check_start
from .planner import CanvasFit, RokenPlanner
from .rollout import PlanConfig, RokenRollout, _Slot, check


def row_name(pc: PlanConfig) -> str:
    """The row a plan section with `select` / `guide` set plays, named as evaluations name it (roken+guided+safe)."""
    return "roken" + ("+guided" if pc.guide else "") + (f"+{pc.select}" if pc.select != "none" else "")


def rollout_config(pc: PlanConfig, planner: str) -> PlanConfig:
    """The plan section for one row: plain `roken` uses one candidate, `roken+X` selects with X (`+guided`: guided
    sampling), e.g. `roken+guided+geodesic`."""
    parts = planner.split("+")[1:]
    guide = "guided" in parts
    select = next((p for p in parts if p != "guided"), "none")
    return replace(pc, select=select, guide=guide, candidates=pc.candidates if select != "none" else 1)


class RokenController:
    """A RokenPlanner with the plan section of one row (guidance, selection, clusters, re-planning)."""

    def __init__(self, planner: RokenPlanner, plan: PlanConfig, task: TaskConfig | None = None,
                 expert: ExpertConfig | None = None):
        self.planner, self.plan, self.task = planner, plan, task or TaskConfig()
        self.rollout = RokenRollout(planner, plan, self.task, expert)

    @classmethod
    def load(cls, checkpoint: str | Path, config: str | Path | None = None, row: str | None = None,
             overrides: list[str] | tuple = (), device: str | None = None) -> "RokenController":
        """checkpoint: a checkpoint directory or run folder; config: a YAML whose plan / task / expert sections
        apply (e.g. configs/deploy.yaml; None: the defaults); row: the planner row (default: the config's first
        `roken*` eval.planner, else `roken` with the plan section's selection); overrides: `--set` strings."""
        from ..config import load_config

        cfg = load_config(config, list(overrides))
        pc = cfg.plan if device is None else replace(cfg.plan, device=device)
        if row is None:
            rows = [p.strip() for p in str(cfg.eval.planner).split(",") if p.strip().startswith("roken")]
            row = rows[0] if rows else row_name(pc)
        if not row.startswith("roken"):
            raise ValueError(f"row {row!r}: a Roken row, e.g. roken, roken+safe, roken+guided+geodesic")
        planner = RokenPlanner.load(checkpoint, pc.device, pc.dtype, pc.which, cfg.task.max_step)
        return cls(planner, rollout_config(pc, row), cfg.task, cfg.expert)

    def start(self, occupancy: np.ndarray, positions: np.ndarray, leader: int, goal, seed: int = 0,
              rescale: bool = False) -> "Team":
        """A team at its start: occupancy (h, w), 1 = obstacle, 1 cell = 1 m, at most the model's canvas (140 m;
        a smaller map is centred on it, walled); positions (n, 2) metres (x along columns); leader: the robot
        given the goal; seed: the noise stream (the same seed and inputs give the same plans). rescale=True fits
        any map to the canvas as the map loaders and `RokenPlanner.plan` do (scaled by an integer, so clearances,
        spacing and speeds hold on the canvas, not in the map's metres)."""
        return Team(self, occupancy, positions, leader, goal, seed, rescale)


class Team:
    """One team's task under a RokenController: what it knows, the plan it carries, its record."""

    def __init__(self, ctl: RokenController, occupancy, positions, leader: int, goal, seed: int = 0,
                 rescale: bool = False):
        occ = np.asarray(occupancy)
        pos = np.asarray(positions, np.float64)
        if occ.ndim != 2 or not occ.size:
            raise ValueError(f"occupancy: a 2-D grid (h, w) with 1 = obstacle, got shape {occ.shape}")
        if pos.ndim != 2 or pos.shape[1] != 2 or not len(pos):
            raise ValueError(f"positions: (n, 2) metres, one row per robot, got shape {pos.shape}")
        if not 0 <= int(leader) < len(pos):
            raise ValueError(f"leader {leader}: the index of the robot given the goal, 0..{len(pos) - 1}")
        check(ctl.plan, ctl.planner, len(pos))  # a team larger than the model needs plan.cluster_size
        self.ctl, S = ctl, ctl.planner.cfg.canvas
        self.fit, self.shape, self.rescale = CanvasFit.of(occ, S, rescale=rescale), occ.shape, rescale
        q, g = self.fit.to_canvas(pos), self.fit.to_canvas(np.reshape(goal, 2))
        for name, p in (("positions", q), ("goal", g[None])):
            if (p < 0).any() or (p >= S).any():
                raise ValueError(f"{name}: outside the map ({occ.shape[1]} x {occ.shape[0]} m, x along columns)")
        gm = GridMap("user", self.fit.occupancy, "user")
        why = check_start(gm, q, ctl.task)  # else every verified candidate fails at its first point: the team holds
        if why or gm.occupancy[int(g[1]), int(g[0])]:
            t = ctl.task
            raise ValueError(f"start refused: {why or 'the goal is in an obstacle cell'} (robots must start at least "
                             f"d_obs_min={t.d_obs_min:g} m from obstacles and d_coll_min={t.d_coll_min:g} m apart, "
                             f"connected within R={t.comm_radius:g} m, and the goal must be free)")
        self._slot = _Slot(0, Task("user", q, g, int(leader), int(seed)), gm, ctl.rollout)
        self._plan: np.ndarray | None = None  # the last plan, on the canvas
        self.held = False  # the last re-plan found no clean candidate: the re-planned robots stand (a safety stop)

    # ------------------------------------------------------------------ the loop
    def replan(self) -> np.ndarray:
        """The next plan (n, H, 2) in the map's metres: the first plan.replan_every moves are the ones to drive."""
        s = self._slot
        s.observe()  # plan.sensing_range > 0: what the team senses of the given map from where it stands
        holds = s.holds
        self._plan = self.ctl.rollout.plan_step([s])[0]
        self.held = s.holds > holds
        return self.fit.from_canvas(self._plan)

    def step(self) -> np.ndarray:
        """Simulation: drive the last plan's first plan.replan_every moves with the harness's step rule (steps of at
        most task.max_step, clipped by their norm); returns the positions now (n, 2)."""
        if self._plan is None:
            raise RuntimeError("step() drives the last plan: call replan() first")
        self._slot.execute(self._plan)
        return self.positions

    def update(self, positions=None, occupancy: np.ndarray | None = None) -> None:
        """Where the robots are now: (n, 2), taken as reached in straight lines over the executed moves' simulator
        steps (plan.replan_every x samples.interval), or (k, n, 2), every simulator step since the last call
        (None: no move since, e.g. after step() in simulation).
        occupancy: the map as the robots know it now (the shape given to start(); cells not yet seen as free, the
        paper's partial observation), from the next re-plan on; the carried plan is kept and verified on it."""
        s, pc, cfg = self._slot, self.ctl.plan, self.ctl.planner.cfg
        if occupancy is not None:
            occ = np.asarray(occupancy)
            if occ.shape != self.shape:
                raise ValueError(f"occupancy: the map of this team is {self.shape}, got {occ.shape}")
            s.use_map(GridMap("user", CanvasFit.of(occ, s.gm.shape[0], rescale=self.rescale).occupancy, "user"))
        if positions is None:
            return
        p = self.fit.to_canvas(positions)
        n = len(s.q)
        if p.shape == (n, 2):
            k = pc.replan_every * cfg.interval
            p = s.q[None] + (p - s.q)[None] * (np.arange(1, k + 1) / k)[:, None, None]
        if p.ndim != 3 or p.shape[1:] != (n, 2):
            raise ValueError(f"positions: ({n}, 2) now, or (k, {n}, 2) every simulator step, got {np.shape(positions)}")
        for row in p:
            s.hist.append(row.astype(np.float32))
            s.q = s.hist[-1].astype(np.float64)
            s.reached = s.reached or s.at_goal()

    # ------------------------------------------------------------------ the record
    @property
    def positions(self) -> np.ndarray:
        return self.fit.from_canvas(self._slot.q)

    @property
    def history(self) -> np.ndarray:
        """(T + 1, n, 2) every simulator step so far, in the map's metres."""
        return self.fit.from_canvas(np.asarray(self._slot.hist, np.float64))

    @property
    def reached(self) -> bool:
        """The leader is within task.eps_goal of the goal (the metric's reach test)."""
        return self._slot.reached

    @property
    def finished(self) -> bool:
        """Reached, or at the expert's step limit for this task (an evaluation episode would end here)."""
        return self._slot.finished

    @property
    def holds(self) -> int:
        return self._slot.holds
