"""Closed-loop Roken: receding-horizon rollout of many episodes at once (paper appendix, "Ablations on
Replanning Frequency"; ARCHITECTURE.md, "Planner").

Per re-plan, for every running episode: the condition of the current state (the known map under partial
observation), one batched model call for all episodes (G candidates each; one call per cluster stage in
clustered rollout), verified selection when asked, then the first `replan_every` chunk moves are executed.
A chunk move spans `interval` simulator steps: each step heads for the point `s / interval` of the way along
the move and is clipped to `max_step` by its norm, and every simulator step is recorded, so the episodes
have the expert's format, step limit and metrics. Episodes run in `batch_size` slots; a finished slot takes the
next task (continuous batching, as the expert does). An episode ends when the leader is within eps_goal of
the goal or at the expert's step limit for the same task.

Each episode draws its noise from its own generator, seeded by (plan.seed, task seed): the same seed gives the
same episodes, and an episode's samples do not depend on which episodes share its batch.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..data.condition import build_condition, known_occupancy, sensed_cells
from ..expert.laplacian import ExpertConfig, LaplacianExpert
from ..world.geometry import pad_for_clearance
from ..world.grid import GridMap
from ..world.tasks import Task, TaskConfig
from .clusters import Cluster, overlapping_clusters
from .guidance import Guide, finite_geodesic, known_fields
from .planner import SAMPLERS, RokenPlanner
from .select import (SELECTIONS, choose, geodesic_field, held_hits, inflated_graph, progress, team_progress,
                     violations)
from .subgoal import subgoal


@dataclass
class PlanConfig:
    checkpoint: str = ""  # checkpoint directory or run folder (evaluate.py --checkpoint)
    which: str = "latest"  # a run folder's "latest" or "best" checkpoint
    replan_every: int = 2  # chunk moves executed before re-planning (paper: 2)
    cluster_size: int = 0  # 0: direct rollout (one call for the team); k >= 2: clustered rollout, clusters <= k
    cluster_new: int = 1  # robots generated per later cluster (1: the paper's bias to 3 given + 1 generated)
    sensing_range: float = 0.0  # metres; 0 = the whole map is known (paper Table 2: 20, 10, 5)
    accumulate: bool = False  # keep what was seen at earlier re-plans (a map built while driving)
    candidates: int = 16  # G candidates per re-plan for verified selection (plain Roken uses 1)
    select: str = "none"  # none | safe | geodesic (roken+safe / roken+geodesic rows)
    fallback: str = "hold"  # no clean candidate: "hold" (the re-planned robots stop: a safety stop) or "fewest"
    verify_moves: int = 0  # chunk moves that must be clean (0 = all; the rest only ranks candidates; select.py)
    verify_steps: bool = False  # also verify every simulator step of the executed moves (executed_points)
    keep_previous: bool = False  # the last chosen plan, shifted by the executed moves, is one more candidate
    select_team: float = 0.0  # ranking adds this x the followers' mean progress to the leader's (0 = leader only)
    geo_inflate: float = 0.0  # > 0: free-space distances (goal term, geodesic ranking) cost more within this many m
    geo_inflate_weight: float = 2.0  # ... of an obstacle, up to 1 + this at its face (select.inflated_graph)
    sampler: str = "ddim"  # ddim | ddpm
    steps: int = 10  # DDIM steps (DDPM uses every diffusion step)
    device: str = "auto"  # auto (cuda where available) | cpu | cuda
    dtype: str = "fp32"  # fp32 | bf16 (autocast)
    batch_size: int = 64  # episodes stepped together
    seed: int = 0
    noise_scale: float = 1.0  # initial noise std of the sampler (< 1: lower temperature)
    subgoal: float = 0.0  # > 0: the leader's goal is a sub-goal this many metres of path ahead (subgoal.py)
    subgoal_sight: bool = True  # the sub-goal is in the leader's sight (False: the path point at plan.subgoal)
    subgoal_after_hold: int = 0  # > 0: the sub-goal only for this many re-plans after a hold (0 = at every one)
    noise: str = "fresh"  # fresh: new noise at every re-plan | episode: one noise draw per episode, reused at each
    # constraint-guided sampling (roken+guided rows; roken/plan/guidance.py): the cost's weights and its descent
    guide: bool = False  # set by the row name roken+guided[+safe]
    guide_scale: float = 1.0  # multiplies the descent step
    guide_steps: int = 10  # the last DDIM steps that are guided (10 = every step of DDIM-10)
    guide_iters: int = 5  # descent iterations at each guided step but the last
    guide_final_iters: int = 30  # descent iterations at the last DDIM step (0: guide_iters)
    guide_lr: float = 0.1  # metres per unit of cost gradient (times guide_scale), <= 0.25 m per point and step
    guide_margin: float = 0.6  # metres added to d_obs_min and d_coll_min, taken off the radius
    guide_obstacle: float = 1.0
    guide_inter: float = 1.0
    guide_connect: float = 1.0
    guide_goal: float = 2.0  # the leader's free-space distance to the goal, mean over the chunk's points
    guide_follow: float = 0.0  # followers' free-space distance to the leader beyond guide_follow_range (0 = off)
    guide_follow_range: float = 10.0  # metres
    guide_exec_weight: float = 4.0  # weight of the executed moves (h < replan_every) in the constraint terms
    record_plans: bool = True  # store each re-plan's chunk with the episode (for the GIF)


def step_toward(q: np.ndarray, prev: np.ndarray, target: np.ndarray, k: int, interval: int,
                max_step: float) -> np.ndarray:
    """Simulator step k (1..interval) of the chunk move prev -> target from positions q (..., 2): toward the
    point k / interval of the way, clipped by its norm (never per component) 0.1 mm inside max_step, so that
    the stored float32 positions (what the metrics read) never step further."""
    d = prev + (target - prev) * (k / interval) - q
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    return d * np.minimum(1.0, (max_step - 1e-4) / np.maximum(norm, 1e-12))


def executed_points(q: np.ndarray, plans: np.ndarray, moves: int, interval: int, max_step: float) -> np.ndarray:
    """The simulator's positions while executing the first `moves` chunk moves of plans (G, m, H, 2) from q (m, 2):
    (G, m, moves * interval, 2), stepped and rounded exactly as _Slot.execute does (what the metrics read).
    Between planned points robots can cut a corner, pass each other closer than at either point, or trade one
    spanning tree for another, so verified selection checks these too (plan.verify_steps)."""
    G = plans.shape[0]
    cur = np.broadcast_to(np.asarray(q, np.float64), (G,) + np.shape(q)).copy()
    prev, out = cur.copy(), []
    for j in range(moves):
        for k in range(1, interval + 1):
            cur = (cur + step_toward(cur, prev, plans[:, :, j], k, interval, max_step)).astype(np.float32)
            out.append(cur)
            cur = cur.astype(np.float64)
        prev = plans[:, :, j].astype(np.float64)
    return np.stack(out, axis=2) if out else np.zeros(plans.shape[:2] + (0, 2), np.float32)


def check(pc: PlanConfig, planner: RokenPlanner | None = None, team_size: int | None = None) -> None:
    """Flags checked before anything runs, naming the flag."""
    if pc.replan_every < 1:
        raise ValueError(f"--replan-every {pc.replan_every}: must be >= 1")
    if not pc.noise_scale > 0:
        raise ValueError(f"plan.noise_scale={pc.noise_scale}: must be > 0 (1 = the model's own distribution)")
    if pc.subgoal < 0 or pc.subgoal_after_hold < 0:
        raise ValueError(f"plan.subgoal={pc.subgoal}, plan.subgoal_after_hold={pc.subgoal_after_hold}: >= 0 (metres "
                         f"of path to look ahead, re-plans after a hold; 0 = the task's goal, at every re-plan)")
    if pc.geo_inflate < 0 or pc.geo_inflate_weight < 0:
        raise ValueError(f"plan.geo_inflate={pc.geo_inflate}, plan.geo_inflate_weight={pc.geo_inflate_weight}: >= 0 "
                         f"(metres of clearance that cost more, and how much more; 0 = plain free-space distance)")
    if pc.verify_moves < 0:
        raise ValueError(f"plan.verify_moves={pc.verify_moves}: 0 (every planned move) or the moves to verify")
    if pc.guide and (pc.sampler != "ddim" or pc.guide_steps < 1 or pc.guide_iters < 1 or pc.guide_scale < 0
                     or pc.guide_final_iters < 0):
        raise ValueError(f"guided sampling needs --sampler ddim and --guide-steps, plan.guide_iters >= 1, "
                         f"plan.guide_final_iters >= 0, --guide-scale >= 0 (got {pc.sampler}, {pc.guide_steps}, "
                         f"{pc.guide_iters}, {pc.guide_final_iters}, {pc.guide_scale})")
    if pc.noise not in ("fresh", "episode"):
        raise ValueError(f"plan.noise={pc.noise!r}: choose fresh or episode")
    if pc.fallback not in ("hold", "fewest"):
        raise ValueError(f"plan.fallback={pc.fallback!r}: choose hold or fewest")
    if pc.select not in SELECTIONS:
        raise ValueError(f"--select {pc.select!r}: choose one of {', '.join(SELECTIONS)}")
    if pc.sampler not in SAMPLERS:
        raise ValueError(f"--sampler {pc.sampler!r}: choose one of {', '.join(SAMPLERS)}")
    if pc.candidates < 1 or pc.steps < 1 or pc.batch_size < 1:
        raise ValueError(f"--candidates {pc.candidates}, --steps {pc.steps}, plan.batch_size {pc.batch_size}: "
                         f"each must be >= 1")
    if pc.cluster_size == 1 or pc.cluster_size < 0:
        raise ValueError(f"--cluster-size {pc.cluster_size}: 0 (direct rollout) or >= 2")
    if pc.sensing_range < 0:
        raise ValueError(f"--sensing-range {pc.sensing_range}: 0 (whole map) or a range in metres")
    if planner is not None:
        H = planner.cfg.horizon
        if pc.replan_every > H:
            raise ValueError(f"--replan-every {pc.replan_every}: a plan has only {H} chunk moves")
        if pc.cluster_size > planner.max_robots:
            raise ValueError(f"--cluster-size {pc.cluster_size}: the model has {planner.max_robots} robot tokens")
        if team_size is not None and not pc.cluster_size and team_size > planner.max_robots:
            raise ValueError(f"{team_size} robots, but the model plans at most {planner.max_robots} in one call "
                             f"(samples.max_robots of {planner.source}); use clustered rollout: --cluster-size 4")


class RokenRollout:
    """Runs tasks of one team size in closed loop with a RokenPlanner."""

    def __init__(self, planner: RokenPlanner, pc: PlanConfig, tc: TaskConfig, expert: ExpertConfig | None = None):
        check(pc, planner)
        self.planner, self.pc, self.tc = planner, pc, tc
        self.limits = LaplacianExpert(expert or ExpertConfig(), tc)  # the same step limit as the expert
        self.G = pc.candidates if pc.select != "none" else 1

    def clusters(self, q: np.ndarray, leader: int) -> list[Cluster]:
        N = len(q)
        if not self.pc.cluster_size or N <= 1:
            return [Cluster(np.arange(N), np.zeros(N, bool), leader)]
        return overlapping_clusters(q, leader, self.tc.comm_radius, self.pc.cluster_size, self.pc.cluster_new)

    def plan_step(self, slots: list["_Slot"]) -> np.ndarray:
        """One re-plan for the given episodes: (len(slots), N, H, 2) the chosen plans in metres."""
        pc, tc, cfg, H = self.pc, self.tc, self.planner.cfg, self.planner.cfg.horizon
        N = len(slots[0].q)
        planned = np.full((len(slots), N, H, 2), np.nan, np.float32)
        done = np.zeros((len(slots), N), bool)
        cl = [self.clusters(s.q, s.task.leader) for s in slots]
        goals = [s.goal() for s in slots]
        for stage in range(max(len(c) for c in cl)):
            rows = [b for b in range(len(slots)) if stage < len(cl[b])]
            T = max(len(cl[b][stage].members) for b in rows)
            conds = []
            for b in rows:
                s, c = slots[b], cl[b][stage]
                goal = goals[b] if c.leader >= 0 else None
                before = s.hist[max(0, len(s.hist) - 1 - cfg.interval)][c.members]  # one chunk move ago
                conds.append(build_condition(s.gm.occupancy, s.q[c.members], c.leader, goal, self.planner.cfg,
                                             given=planned[b][c.members], fixed=c.fixed, seen=s.seen, tokens=T,
                                             previous=before))
            outside = self.outside([slots[b] for b in rows], [cl[b][stage] for b in rows],
                                   [planned[b] for b in rows], [done[b] for b in rows]) if pc.guide else None
            guide = self.guide([slots[b] for b in rows], conds, outside) if pc.guide else None
            out = self.planner.sample(conds, self.G, pc.sampler, pc.steps, [slots[b].generator(stage) for b in rows],
                                      guide, pc.guide_steps, pc.noise_scale)
            for j, b in enumerate(rows):
                s, c = slots[b], cl[b][stage]
                m = len(c.members)
                cand = out[j, :, :m]  # (G, m, H, 2)
                if pc.keep_previous and pc.select != "none" and s.last is not None:
                    cand = np.concatenate([cand, s.carried(c, cand[0])[None]], axis=0)  # (G + 1, m, H, 2)
                G = len(cand)
                g = 0
                if pc.select != "none":
                    start = np.broadcast_to(s.q[c.members][None, :, None], (G, m, 1, 2))
                    paths = np.concatenate([start, cand], axis=2)  # (G, m, H+1, 2)
                    others = np.flatnonzero(done[b] & ~np.isin(np.arange(N), c.members))
                    other_paths = np.concatenate([s.q[others][:, None], planned[b][others]], axis=1)
                    count = lambda a, b: violations(a, s.padded_known, b, tc.d_obs_min, tc.d_coll_min,  # noqa: E731
                                                    tc.comm_radius)
                    late = None
                    if 0 < pc.verify_moves < H:  # the verified prefix (start + V moves) and the rest, counted apart
                        V = pc.verify_moves + 1
                        viol = count(paths[:, :, :V], other_paths[:, :V])
                        late = count(paths[:, :, V:], other_paths[:, V:])
                    else:
                        viol = count(paths, other_paths)
                    if pc.verify_steps:  # the executed moves at the simulator's resolution, the metrics' own
                        step = lambda p, q0: executed_points(q0, p, pc.replan_every, cfg.interval,  # noqa: E731
                                                             tc.max_step)
                        viol = viol + count(step(cand, s.q[c.members]),
                                            step(planned[b][others][None], s.q[others])[0])
                    # later clusters' robots where they stand: the moves executed before they re-plan keep clear
                    held = ~done[b] & ~np.isin(np.arange(N), c.members)
                    viol = viol + held_hits(paths[:, :, 1:pc.replan_every + 1], s.q[held], tc.d_coll_min)
                    prog = np.zeros(G)
                    field = s.geodesic if pc.select == "geodesic" else None
                    if c.leader >= 0 and not c.fixed[c.leader]:
                        prog = progress(s.q[s.task.leader], cand[:, c.leader, -1], s.task.goal, field)
                    followers = [i for i in range(m) if i != c.leader and not c.fixed[i]] if pc.select_team > 0 \
                        else []
                    if followers:
                        prog = prog + pc.select_team * team_progress(s.q[c.members[followers]],
                                                                     cand[:, followers, -1], s.task.goal, field)
                    g = choose(viol, prog, late)
                    if viol[g] > 0 and pc.fallback == "hold":
                        cand = np.broadcast_to(s.q[c.members][None, :, None], cand.shape)
                        s.holds += 1
                        s.subgoal_left = pc.subgoal_after_hold
                gen = c.members[~c.fixed]
                planned[b][gen] = cand[g][~c.fixed]
                done[b][gen] = True
        if pc.keep_previous:  # the next re-plan's carried candidate (_Slot.carried)
            for s, plan in zip(slots, planned):
                s.last = plan.copy()
        return planned

    def outside(self, slots: list["_Slot"], clusters: list[Cluster], planned: list[np.ndarray],
                done: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
        """The team's robots outside each prompt's cluster, for the guidance's inter-robot term: (points (B, K, H,
        2), weights (B, K, H)). Robots planned in an earlier cluster count with their plans at every move; robots of
        later clusters where they stand, over the executed moves only (they may hold there: a later cluster with
        no clean candidate does, and the later moves are re-planned before they run). None in direct rollout."""
        N, H = len(slots[0].q), self.planner.cfg.horizon
        K = N - min(len(c.members) for c in clusters)
        if K == 0:
            return None
        pts, wts = np.zeros((len(slots), K, H, 2), np.float32), np.zeros((len(slots), K, H), np.float32)
        for j, (s, c) in enumerate(zip(slots, clusters)):
            others = np.setdiff1d(np.arange(N), c.members)
            now = np.broadcast_to(s.q[others][:, None], (len(others), H, 2))
            pts[j, :len(others)] = np.where(done[j][others][:, None, None], planned[j][others], now)
            wts[j, :len(others)] = np.where(done[j][others][:, None], 1.0, np.arange(H)[None] < self.pc.replan_every)
        return pts, wts

    def guide(self, slots: list["_Slot"], conds: list[dict], outside=None) -> Guide:
        """The guidance of one batched model call: each prompt's known-map fields, starts and masks."""
        real = np.stack([c["robot_mask"] > 0 for c in conds])
        leader = np.array([int(np.argmax(c["goal_mask"])) if c["goal_mask"].any() else -1 for c in conds])
        return Guide(self.pc, self.tc, self.planner.cfg, np.stack([c["start"] for c in conds]), real,
                     real & ~(np.stack([c["traj_mask"] for c in conds]) > 0), leader,
                     np.stack([s.fields[0] for s in slots]), np.stack([s.fields[1] for s in slots]), self.G,
                     self.planner.device, np.stack([s.leader_field() for s in slots]) if self.pc.guide_follow > 0
                     else None, outside)

    def run(self, tasks: list[Task], maps: dict[str, GridMap], prefixes: list[np.ndarray | None] | None = None):
        """Yield (task index, positions (T+1, N, 2) float32, info) as episodes finish (not in task order).
        prefixes[i] (K+1, N, 2), when given, is task i's first K steps already driven by another planner (the
        expert, benchmarks/start_handoff.py): the episode goes on from its last row, its last move as history, under
        the task's own step limit, and the returned positions include it."""
        if not tasks:
            return
        N = tasks[0].num_robots
        if any(t.num_robots != N for t in tasks):
            raise ValueError("RokenRollout.run takes tasks of one team size; group them first")
        check(self.pc, self.planner, N)
        pc = self.pc
        pending = list(range(len(tasks)))[::-1]
        slots: list[_Slot | None] = [None] * min(pc.batch_size, len(tasks))

        def fill(k: int):
            i = pending.pop()
            slots[k] = _Slot(i, tasks[i], maps[tasks[i].map_id], self, None if prefixes is None else prefixes[i])

        for k in range(len(slots)):
            fill(k)
        while True:
            for k in range(len(slots)):
                while slots[k] is not None and slots[k].finished:  # (a prefix may end an episode before any plan)
                    s = slots[k]
                    yield s.index, np.asarray(s.hist, np.float32), s.info()
                    slots[k] = None
                    if pending:
                        fill(k)
            live = [s for s in slots if s is not None]
            if not live:
                return
            for s in live:
                s.observe()
            plans = self.plan_step(live)
            for s, plan in zip(live, plans):
                s.execute(plan)


class _Slot:
    """One running episode: state, what it knows, its noise generator and its record."""

    def __init__(self, index: int, task: Task, gm: GridMap, ro: RokenRollout, prefix: np.ndarray | None = None):
        self.index, self.task, self.gm, self.ro = index, task, gm, ro
        if gm.shape != (ro.planner.cfg.canvas,) * 2:
            raise ValueError(f"map {gm.map_id} is {gm.shape}; the model's canvas is {ro.planner.cfg.canvas}: "
                             f"fit maps to the canvas (the harness's map loaders do)")
        self.q = np.asarray(task.starts, np.float64).copy()
        self.hist = [self.q.astype(np.float32)]
        if prefix is not None:
            if not np.allclose(prefix[0], self.q, atol=1e-4):
                raise ValueError(f"task {index}: its prefix does not start at the task's starts")
            self.hist = list(np.asarray(prefix, np.float32))
            self.q = self.hist[-1].astype(np.float64)
        self.limit = ro.limits.step_limit(task, gm)
        seed = np.random.SeedSequence([ro.pc.seed, int(task.seed), len(self.q)]).generate_state(2)
        self.seed = int(seed[0]) << 32 | int(seed[1])
        self.gen = torch.Generator().manual_seed(self.seed)
        self.seen = None
        self.plans: list[np.ndarray] = []
        self.last: np.ndarray | None = None  # the plan (N, H, 2) chosen at the last re-plan (plan.keep_previous)
        self.plan_steps: list[int] = []
        self.reached = self.at_goal()  # a prefix may end at the goal already
        self.holds = 0  # re-plans where no candidate was clean and the team held position
        self.subgoal_left = 0  # re-plans left toward the sub-goal (plan.subgoal_after_hold)
        self.use_map(gm)

    def use_map(self, gm: GridMap) -> None:
        """The map the team knows and what the goal terms read from it, built once per map (observe() rebuilds them
        for a sensed one; RokenController.Team.update for a map the user's robots have updated)."""
        pc, self.gm = self.ro.pc, gm
        self.padded_known = gm.padded
        self.geodesic = None
        # the free-space graph of the known map that the goal fields use: clearance-costed with plan.geo_inflate,
        # None = build a plain one
        uses = pc.guide or pc.select == "geodesic" or pc.subgoal > 0
        self.goal_graph = inflated_graph(gm.occupancy, pc.geo_inflate, pc.geo_inflate_weight) \
            if pc.geo_inflate > 0 and uses and not pc.sensing_range else gm.free_graph
        if (pc.select == "geodesic" or pc.subgoal > 0) and not pc.sensing_range:
            self.geodesic = geodesic_field(gm.occupancy, self.task.goal, self.goal_graph)
        self.fields = known_fields(gm.occupancy, self.task.goal, self.goal_graph) if pc.guide else None

    def generator(self, stage: int) -> torch.Generator:
        """The noise of this re-plan: the episode's running stream, or (plan.noise=episode) the same draw at every
        re-plan, so that consecutive plans start from one noise and stay consistent (no dithering between them)."""
        if self.ro.pc.noise == "episode":
            return torch.Generator().manual_seed(self.seed + stage)
        return self.gen

    def leader_field(self) -> np.ndarray:
        """(S, S) free-space distance to the leader's current position on the known map (the follow term)."""
        known = self.gm.occupancy if self.seen is None else known_occupancy(self.gm.occupancy, self.seen)
        return finite_geodesic(known, self.q[self.task.leader], self.goal_graph)

    def goal(self) -> np.ndarray:
        """The leader's goal for this re-plan: the task's, or (plan.subgoal) a sub-goal along the free-space path."""
        pc = self.ro.pc
        if pc.subgoal <= 0 or (pc.subgoal_after_hold > 0 and self.subgoal_left <= 0):
            return np.asarray(self.task.goal, np.float64)
        self.subgoal_left -= 1
        return subgoal(self.geodesic, self.padded_known, self.q[self.task.leader], self.task.goal, pc.subgoal,
                       sight=pc.subgoal_sight)

    def carried(self, c: Cluster, fresh: np.ndarray) -> np.ndarray:
        """The last chosen plan of cluster c's robots with its executed moves dropped and its end point held
        (m, H, 2): a candidate that keeps the team on a course already verified (plan.keep_previous, the warm start
        of sampling-based MPC). At a 3 m gap the fresh candidates that move forward bunch the team at their late
        points while those that are clean back off; the carried plan goes on through where it was clean. Given
        robots keep this re-plan's plans (fresh: any candidate (m, H, 2) of it)."""
        r = self.ro.pc.replan_every
        prev = self.last[c.members]
        out = np.concatenate([prev[:, r:], np.repeat(prev[:, -1:], r, axis=1)], axis=1)
        out[c.fixed] = fresh[c.fixed]
        return out.astype(fresh.dtype)

    @property
    def finished(self) -> bool:
        return self.reached or len(self.hist) - 1 >= self.limit

    def observe(self) -> None:
        """Update what the team knows before a re-plan (partial observation only)."""
        pc = self.ro.pc
        if not pc.sensing_range:
            return
        now = sensed_cells(self.q, self.gm.shape[0], pc.sensing_range)
        self.seen = now if self.seen is None or not pc.accumulate else self.seen | now
        known = known_occupancy(self.gm.occupancy, self.seen)
        self.goal_graph = inflated_graph(known, pc.geo_inflate, pc.geo_inflate_weight) if pc.geo_inflate > 0 \
            else None
        if pc.guide:  # the guidance sees the known map only
            self.fields = known_fields(known, self.task.goal, self.goal_graph)
        if pc.select != "none" or pc.subgoal > 0:
            self.padded_known = pad_for_clearance(known)
            if pc.select == "geodesic" or pc.subgoal > 0:
                self.geodesic = geodesic_field(known, self.task.goal, self.goal_graph)

    def execute(self, plan: np.ndarray) -> None:
        """The first replan_every chunk moves of plan (N, H, 2), one simulator step at a time."""
        pc, tc, cfg = self.ro.pc, self.ro.tc, self.ro.planner.cfg
        if pc.record_plans:
            self.plans.append(plan.astype(np.float32))
            self.plan_steps.append(len(self.hist) - 1)
        prev = self.q.copy()
        for j in range(pc.replan_every):
            for k in range(1, cfg.interval + 1):
                step = step_toward(self.q, prev, plan[:, j], k, cfg.interval, tc.max_step)
                self.hist.append((self.q + step).astype(np.float32))
                self.q = self.hist[-1].astype(np.float64)
                if self.at_goal():
                    self.reached = True
                if self.finished:
                    return
            prev = plan[:, j].astype(np.float64)

    def at_goal(self) -> bool:
        """The metric's reach test on the last stored (float32) position of the leader."""
        lead = self.hist[-1][self.task.leader].astype(np.float64)
        return bool(np.linalg.norm(lead - np.asarray(self.task.goal, np.float64)) <= self.ro.tc.eps_goal)

    def info(self) -> dict:
        return {"reached": self.reached, "limit": self.limit, "holds": self.holds, "plan_steps": self.plan_steps,
                "plans": np.asarray(self.plans, np.float32)}
