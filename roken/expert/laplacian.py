"""The Laplacian expert, batched: many teams stepped in one array program.

Per step and team (expert.md; paper appendix "Dataset Collection Pipeline"):
  1. weighted communication graph A_ij = alpha(d_ij) gamma_ij (roken.world.graph);
  2. minimum spanning tree with cost -log A_ij, switched only when better by a margin (hysteresis);
  3. lambda_2 and the eigenspace projector of the tree Laplacian, analytic d lambda_2 / d q;
  4. connectivity field u^c = (1/(lambda_2 - lambda_2_min)^2) d lambda_2 / d q (gain capped);
  5. followers move by u^c only (lazy movement); the leader mixes u^c with the unit vector to a look-ahead
     point on its smoothed A* reference and slows as lambda_2 approaches its minimum;
  6. every step is at most max_step and filtered: a step that would come within the safety margins of an
     obstacle or a robot, or disconnect the team, is slid, shortened or dropped.
Structural fix from expert.md: a follower whose tree parent is out of sight is pulled along the free-space
path toward it (the most promising visible point of the parent's recent trail or of the leader's
reference) instead of straight into the obstacle between them.

Teams run in `batch_size` slots; a finished slot is refilled with the next episode (continuous batching),
so long episodes do not leave the batch idle.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..world.geometry import bilinear, clearance, line_of_sight
from ..world.graph import (WeightParams, connected, edge_weights, fiedler, lambda2_gradient,
                           minimum_spanning_tree, tree_parents)
from ..world.grid import GridMap
from ..world.paths import GridGraph
from ..world.tasks import Task, TaskConfig, TaskError, check_start
from ..world.paths import path_length
from . import dart
from .reference import leader_reference
from .smoothing import smooth_episode


@dataclass
class ExpertConfig:
    comm_full: float = 11.0  # d_min of the communication roll-off (alpha = 1 below)
    coll_full: float = 4.0  # d_coll_max: robot-robot factor reaches 1 here
    obs_full: float = 1.6  # obstacle factor reaches 1 at this clearance
    lambda2_min_frac: float = 0.05  # lambda_2_min as a fraction of lambda_2 of the unit path graph
    gain_max: float = 1e4
    follower_sat: float = 0.05  # |u^c| * (N / 4) at which a follower moves a full step
    follower_deadband: float = 0.02  # fraction of a full step below which a follower stays put
    leader_conn_weight: float = 0.5  # lambda_c (leader), with lambda_r = 1
    leader_slow: float = 0.45  # lambda_2 / lambda_2(unit tree) below which the leader slows ...
    leader_stop: float = 0.12  # ... and at which it stops
    lookahead: float = 2.0  # m along the reference
    ref_clearance: float = 1.6  # string pulling keeps this clearance (m)
    tree_switch_margin: float = 0.3  # switch trees when -sum log A improves by this much
    stall_steps: int = 40  # no leader progress for this many steps: re-plan the tree
    geodesic_pull: bool = True
    los_clearance: float = 1.1  # clearance a straight pull must keep to count as line of sight
    pull_limit: float = 35.0  # m: geodesic search radius around the parent
    pull_hops: int = 24  # cells of the geodesic path considered for the look-ahead target
    pull_refresh: int = 12  # steps a pull target is reused
    inertia: float = 0.5  # fraction of the previous step kept in the next one
    # The first step's "previous step": 0 starts the team from rest (a task's start); True takes the first command
    # itself, so an expert restarted mid-motion moves at once at the speed it would have kept (restarted labels
    # without the ramp from rest, README "Markov labels")
    warm_start: bool = False
    margin_obs: float = 0.08  # safety filter margins on top of d_obs_min / d_coll_min
    margin_coll: float = 0.08
    step_limit_factor: float = 3.0  # episode step limit = factor * A* length / max_step + extra
    step_limit_extra: int = 60
    smooth_window: int = 5  # moving-average window of the recorded trajectories (odd; 1 = off)
    # DART (roken/expert/dart.py): once per episode the team is pushed off course for `disturb_steps` steps
    # (`disturb` m/step; mode random or approach) and the expert's recovery is recorded; 0 = off.
    disturb: float = 0.0
    disturb_steps: int = 8
    disturb_mode: str = "random"
    batch_size: int = 64


@dataclass
class ExpertEpisode:
    positions: np.ndarray  # (T+1, N, 2) float32
    reached: bool
    steps: int
    reference_length: float
    info: dict = field(default_factory=dict)


def unit_path_lambda2(n: int) -> float:
    return 2.0 * (1.0 - np.cos(np.pi / max(n, 2)))


class LaplacianExpert:
    """Runs tasks of one team size through the batched controller."""

    def __init__(self, cfg: ExpertConfig, task_cfg: TaskConfig):
        dart.check(cfg.disturb, cfg.disturb_steps, cfg.disturb_mode)
        self.cfg = cfg
        self.tc = task_cfg
        self.wp = WeightParams(comm_radius=task_cfg.comm_radius, comm_full=cfg.comm_full,
                               coll_min=task_cfg.d_coll_min, coll_full=cfg.coll_full,
                               obs_min=task_cfg.d_obs_min, obs_full=cfg.obs_full)

    # ------------------------------------------------------------------ episode set-up
    def prepare(self, task: Task, gm: GridMap):
        """(leader reference (L, 2), its length, the episode step limit) of a task; every baseline uses them."""
        ref = leader_reference(gm, task.starts[task.leader], task.goal, self.cfg.ref_clearance,
                               spacing=self.tc.max_step / 2)
        if ref is None:
            ref = np.stack([task.starts[task.leader], task.goal]).astype(np.float64)
        L = path_length(ref)
        limit = int(np.ceil(self.cfg.step_limit_factor * L / self.tc.max_step)) + self.cfg.step_limit_extra
        return ref, L, limit

    def step_limit(self, task: Task, gm: GridMap) -> int:
        """A task's episode step limit; every planner uses the expert's, so time-outs mean the same thing."""
        return self.prepare(task, gm)[2]

    # ------------------------------------------------------------------ main loop
    def run(self, tasks: list[Task], maps: dict[str, GridMap]):
        """Yield (task index, ExpertEpisode) as episodes finish (not in task order)."""
        if not tasks:
            return
        N = tasks[0].num_robots
        if any(t.num_robots != N for t in tasks):
            raise ValueError("LaplacianExpert.run takes tasks of one team size; group them first")
        cfg, tc = self.cfg, self.tc
        for i, t in enumerate(tasks):  # a start the controller cannot leave cleanly is refused, with the reason
            why = check_start(maps[t.map_id], np.asarray(t.starts, np.float64), tc)
            if why:
                raise TaskError(f"task {i} on map {t.map_id}: the expert cannot start there: {why} (a start must "
                                f"keep d_obs_min={tc.d_obs_min:g} m clearance and d_coll_min={tc.d_coll_min:g} m "
                                f"spacing, and be connected within R={tc.comm_radius:g} m)")
        S = min(cfg.batch_size, len(tasks))
        H, W = maps[tasks[0].map_id].shape
        sdf = np.zeros((S, H, W), np.float32)
        padded = np.zeros((S,) + maps[tasks[0].map_id].padded.shape, bool)
        pending = list(range(len(tasks)))[::-1]
        slot_task = np.full(S, -1)
        prepared = [None] * len(tasks)
        limits_all = []
        for i, t in enumerate(tasks):
            prepared[i] = self.prepare(t, maps[t.map_id])
            limits_all.append(prepared[i][2])
        lcap = max(len(r[0]) for r in prepared)
        st = _SlotState(S, N, lcap, max(limits_all) + 1)
        ref_len = np.zeros(S)
        limits = np.zeros(S, np.int64)
        lam2_min = cfg.lambda2_min_frac * unit_path_lambda2(N)
        eye = np.eye(N, dtype=bool)[None]
        sl = np.arange(S)

        def fill(s: int):
            i = pending.pop()
            t, gm = tasks[i], maps[tasks[i].map_id]
            if gm.shape != (H, W):
                raise ValueError(f"map {gm.map_id} is {gm.shape}, expected {(H, W)}: fit maps to the canvas")
            sdf[s] = gm.sdf
            padded[s] = gm.padded
            ref, L, limit = prepared[i]
            ref_len[s], limits[s] = L, limit
            slot_task[s] = i
            st.reset(s, t, ref)
            st.graphs[s] = gm.safe_graph
            if cfg.disturb > 0:  # DART: where and how this episode is pushed off course, from the task's seed
                st.dist_at[s], st.dist_v[s], st.dist_who[s] = dart.draw(t.seed, L, tc.max_step, N, cfg.disturb)

        for s in range(S):
            fill(s)
        active = np.ones(S, bool)
        while active.any():
            q = st.q
            obs, obs_grad = bilinear(sdf, q, np.broadcast_to(sl[:, None], (S, N)), with_grad=True)
            ew = edge_weights(q, obs.astype(np.float64), obs_grad.astype(np.float64), self.wp)
            # -- tree with hysteresis
            comm = (ew.dist <= tc.comm_radius) & ~eye
            cost = np.where(comm, -np.log(np.maximum(ew.A, 1e-9)), np.inf)
            new_tree = minimum_spanning_tree(cost)
            cur = np.where(st.tree, cost, 0.0).sum(axis=(1, 2)) / 2
            cur = np.where((st.tree & ~comm).any(axis=(1, 2)) | ~st.has_tree, np.inf, cur)
            new = np.where(new_tree, cost, 0.0).sum(axis=(1, 2)) / 2
            switch = ~np.isfinite(cur) | (new < cur - cfg.tree_switch_margin) | st.force_replan
            if switch.any() and N > 1:
                st.tree[switch] = new_tree[switch]
                st.has_tree[switch] = True
                st.force_replan[switch] = False
                unit = st.tree[switch].astype(np.float64)
                st.lam2_unit[switch] = np.linalg.eigvalsh(unit.sum(-1)[..., None] * np.eye(N) - unit)[:, 1]
            if N > 1:
                lam2, Smat = fiedler(ew.A * st.tree)
                grad = lambda2_gradient(ew, st.tree, Smat)
                if cfg.geodesic_pull:
                    parents = tree_parents(st.tree, st.leader)
                    grad += self._geodesic_correction(q, ew, Smat, st, parents, sdf)
            else:  # a lone robot: no graph, only the reference
                lam2, grad = np.ones(S), np.zeros_like(q)
            gain = np.minimum(1.0 / np.maximum(lam2 - lam2_min, 1e-6) ** 2, cfg.gain_max)
            uc = gain[:, None, None] * grad
            # -- followers: saturating response with a dead band (lazy movement)
            mag = np.linalg.norm(uc, axis=-1)
            frac = np.minimum(mag / (cfg.follower_sat * 4.0 / N), 1.0)
            frac = np.where(frac < cfg.follower_deadband, 0.0, frac)
            dir_c = uc / np.maximum(mag, 1e-12)[..., None]
            v = tc.max_step * frac[..., None] * dir_c
            # -- leader: reference pursuit, slowed as lambda_2 approaches its minimum
            lq = q[sl, st.leader]
            target = self._advance_reference(st, lq)
            to_t = target - lq
            dist_t = np.linalg.norm(to_t, axis=-1)
            un = to_t / np.maximum(dist_t, 1e-9)[:, None]
            if N > 1:  # slow-down on the communication part only: a robot brushing a wall must not stop the team
                at = ew.alpha * st.tree
                lam2_comm = np.linalg.eigvalsh(at.sum(-1)[..., None] * np.eye(N) - at)[:, 1]
                ratio = lam2_comm / np.maximum(st.lam2_unit, 1e-9)
            else:
                ratio = np.ones(S)
            speed = np.clip((ratio - cfg.leader_stop) / (cfg.leader_slow - cfg.leader_stop), 0.0, 1.0)
            mix = speed[:, None] * un + cfg.leader_conn_weight * frac[sl, st.leader][:, None] * dir_c[sl, st.leader]
            mix_n = np.linalg.norm(mix, axis=-1)
            lstep = np.minimum(tc.max_step * np.minimum(mix_n, 1.0), dist_t)  # do not overshoot the goal
            v[sl, st.leader] = mix / np.maximum(mix_n, 1e-12)[:, None] * lstep[:, None]
            if cfg.disturb > 0:  # DART's push, capped at a full step; the filter below still keeps it feasible
                push = ((st.t >= st.dist_at) & (st.t < st.dist_at + cfg.disturb_steps))[:, None, None]
                off, held = dart.push(q, st.dist_v, st.dist_who, cfg.disturb_mode, cfg.disturb)
                v = np.where(push & held[..., None], 0.0, v) + np.where(push, off, 0.0)
                n_v = np.linalg.norm(v, axis=-1, keepdims=True)
                v = v * np.minimum(1.0, tc.max_step / np.maximum(n_v, 1e-12))
            # -- inertia damps the period-2 chatter of opposing fields, then the safety filter
            prev = np.where((st.t == 0)[:, None, None], v, st.v_prev) if cfg.warm_start else st.v_prev
            v = (1.0 - cfg.inertia) * v + cfg.inertia * prev
            step = self._filter(q, v, obs_grad, padded, st.leader)
            st.v_prev = step
            step[~active] = 0.0
            st.q = q + step
            st.t += active
            # -- bookkeeping: progress, stalls, termination
            lead_goal = np.linalg.norm(st.q[sl, st.leader] - st.goal, axis=-1)
            st.stall = np.where(st.prog > st.best_prog, 0, st.stall + 1)
            st.best_prog = np.maximum(st.best_prog, st.prog)
            st.force_replan |= st.stall == cfg.stall_steps
            st.hist[sl, st.t] = st.q
            done = active & ((lead_goal <= tc.eps_goal * 0.9) | (st.t >= limits))
            for s in np.nonzero(done)[0]:
                i = int(slot_task[s])
                raw = st.hist[s, :st.t[s] + 1].copy()
                reached = bool(lead_goal[s] <= tc.eps_goal)
                gm = maps[tasks[i].map_id]
                pos, smoothed = smooth_episode(raw, gm, tasks[i], tc, cfg.smooth_window)
                yield i, ExpertEpisode(pos, reached, int(st.t[s]), float(ref_len[s]),
                                       {"smoothed": smoothed, "limit": int(limits[s]),
                                        "disturbed_at": int(st.dist_at[s]) if cfg.disturb > 0 else -1})
                if pending:
                    fill(s)
                else:
                    active[s] = False

    # ------------------------------------------------------------------ pieces
    def _advance_reference(self, st: "_SlotState", lq: np.ndarray) -> np.ndarray:
        st.prog, target = advance_reference(st.ref, st.ref_n, st.prog, lq, self.cfg.lookahead, self.tc.max_step)
        return target

    def _geodesic_correction(self, q, ew, Smat, st, parents, sdf) -> np.ndarray:
        """Redirect the tree-edge pull of followers whose parent is out of sight (see module doc).

        The target is the farthest point of the geodesic (octile, safe-cell) path from the follower to its
        parent that the follower can see: it goes around the obstacle between them, not into it.
        Targets are cached for `pull_refresh` steps.
        """
        cfg = self.cfg
        fix = np.zeros_like(q)
        b, m = np.nonzero(parents >= 0)
        p = parents[b, m]
        coef = ew.dalpha[b, m, p] * ew.gamma[b, m, p] * Smat[b, m, p]
        keep = coef < 0  # only a stretched edge pulls
        b, m, p, coef = b[keep], m[keep], p[keep], coef[keep]
        if len(b) == 0:
            return fix
        los = line_of_sight(sdf, q[b, m], q[b, p], cfg.los_clearance, spacing=0.5, index=b)
        b, m, p, coef = b[~los], m[~los], p[~los], coef[~los]
        if len(b) == 0:
            return fix
        stale = (st.pull_age[b, m] >= cfg.pull_refresh) | (st.pull_parent[b, m] != p)
        if stale.any():
            bs, ms, ps = b[stale], m[stale], p[stale]
            tgt, ok = self._pull_targets(st, q, bs, ms, ps, sdf)
            st.pull_target[bs, ms] = tgt
            st.pull_valid[bs, ms] = ok
            st.pull_parent[bs, ms] = ps
            st.pull_age[bs, ms] = 0
        st.pull_age += 1
        ok = st.pull_valid[b, m]
        b, m, p, coef = b[ok], m[ok], p[ok], coef[ok]
        d = q[b, m] - st.pull_target[b, m]
        e_new = d / np.maximum(np.linalg.norm(d, axis=-1), 1e-9)[:, None]
        np.add.at(fix, (b, m), coef[:, None] * (e_new - ew.unit[b, m, p]))
        return fix

    def _pull_targets(self, st, q, b, m, p, sdf):
        """Geodesic pull targets: a distance-limited Dijkstra from each parent's cell on the safe-cell graph
        (shared by its children), the path from the follower's cell back along the predecessors, and the
        farthest point of its first `pull_hops` cells still in line of sight of the follower."""
        cfg = self.cfg
        M = len(b)
        pts = np.full((M, cfg.pull_hops, 2), np.nan)
        for key in set(zip(b.tolist(), p.tolist())):
            s_, p_ = key
            g = st.graphs[s_]
            src = g.nearest_node(q[s_, p_])
            if src < 0:
                continue
            pred = g.predecessors_within(src, cfg.pull_limit)
            ks = np.nonzero((b == s_) & (p == p_))[0]
            n = np.array([g.nearest_node(q[s_, m[k]]) for k in ks])
            for h in range(cfg.pull_hops):  # walk all children's paths toward the parent at once
                n = np.where(n >= 0, pred[np.maximum(n, 0)], -1)
                if not (n >= 0).any():
                    break
                live = n >= 0
                pts[ks[live], h] = g.cells[n[live]][:, ::-1] + 0.5
        has = ~np.isnan(pts[..., 0])
        filled = np.where(has[..., None], pts, q[b, m][:, None])
        vis = line_of_sight(sdf, q[b, m][:, None], filled, cfg.los_clearance, spacing=0.5, index=b[:, None])
        vis &= has
        far = cfg.pull_hops - 1 - np.argmax(vis[:, ::-1], axis=1)
        ok = vis.any(axis=1)
        tgt = filled[np.arange(M), far]
        return tgt, ok

    def _filter(self, q, v, obs_grad, padded, leader):
        """Choose per robot the first safe of (v, v slid along the wall, v/2, v/4, 0), then resolve
        robot-robot conflicts and disconnections by dropping steps (the current state is assumed valid)."""
        tc, cfg = self.tc, self.cfg
        S, N, _ = q.shape
        sl = np.arange(S)
        n = obs_grad / np.maximum(np.linalg.norm(obs_grad, axis=-1, keepdims=True), 1e-9)
        into = np.minimum((v * n).sum(-1), 0.0)[..., None]
        slide = v - into * n
        thr = tc.d_obs_min + cfg.margin_obs
        idx = np.broadcast_to(sl[:, None], (S, N))
        c_old = clearance(padded, q, idx)
        c_new = clearance(padded, q + v, idx)
        step = v.copy()
        bad = (c_new < thr) & (c_new < c_old)
        if bad.any():  # fall-backs only for the few robots whose direct step is unsafe
            bb, mm = np.nonzero(bad)
            vb, sb = v[bb, mm], slide[bb, mm]
            cand = np.stack([sb, 0.5 * vb, 0.25 * vb, 0.5 * sb, np.zeros_like(vb)], axis=1)  # (M, K, 2)
            cc = clearance(padded, q[bb, mm][:, None] + cand, np.broadcast_to(bb[:, None], cand.shape[:2]))
            ok = (cc >= thr) | (cc >= c_old[bb, mm][:, None])
            ok[:, -1] = True
            step[bb, mm] = cand[np.arange(len(bb)), np.argmax(ok, axis=1)]
        d_old = np.linalg.norm(q[:, :, None] - q[:, None], axis=-1)
        off = ~np.eye(N, dtype=bool)[None]
        for _ in range(2 * N + 2):
            nq = q + step
            d = np.linalg.norm(nq[:, :, None] - nq[:, None], axis=-1)
            bad = off & (d < tc.d_coll_min + cfg.margin_coll) & (d < d_old)
            moving = np.linalg.norm(step, axis=-1) > 0
            viol = bad.any(axis=2) & moving
            conn = connected(d, tc.comm_radius) | ~connected(d_old, tc.comm_radius)
            if not viol.any() and conn.all():
                break
            step[viol] = 0.0
            bad_team = ~conn & ~viol.any(axis=1)
            lead_moving = np.linalg.norm(step[sl, leader], axis=-1) > 0
            first = bad_team & lead_moving
            step[sl[first], leader[first]] = 0.0
            step[bad_team & ~lead_moving] = 0.0
        return step


def advance_reference(ref: np.ndarray, ref_n: np.ndarray, prog: np.ndarray, lq: np.ndarray, lookahead: float,
                      max_step: float) -> tuple[np.ndarray, np.ndarray]:
    """Project each leader lq (S, 2) onto its reference ref (S, L, 2) (ref_n points) near its progress index
    prog (S,); returns (the new progress index, the look-ahead point `lookahead` m further on)."""
    S = len(lq)
    look = int(round(lookahead / (max_step / 2)))  # references are resampled every max_step / 2
    sl = np.arange(S)
    win = np.minimum(prog[:, None] + np.arange(24), ref_n[:, None] - 1)  # (S, 24)
    d = np.linalg.norm(ref[sl[:, None], win] - lq[:, None], axis=-1)
    prog = win[sl, np.argmin(d, axis=1)]
    return prog, ref[sl, np.minimum(prog + look, ref_n - 1)]


class _SlotState:
    def __init__(self, S: int, N: int, ref_cap: int, t_cap: int):
        self.q = np.zeros((S, N, 2))
        self.goal = np.zeros((S, 2))
        self.leader = np.zeros(S, np.int64)
        self.tree = np.zeros((S, N, N), bool)
        self.has_tree = np.zeros(S, bool)
        self.force_replan = np.zeros(S, bool)
        self.lam2_unit = np.ones(S)
        self.prog = np.zeros(S, np.int64)
        self.best_prog = np.zeros(S, np.int64)
        self.stall = np.zeros(S, np.int64)
        self.t = np.zeros(S, np.int64)
        self.v_prev = np.zeros((S, N, 2))
        self.ref = np.zeros((S, ref_cap, 2))
        self.ref_n = np.ones(S, np.int64)
        self.hist = np.zeros((S, t_cap + 1, N, 2))
        self.pull_target = np.zeros((S, N, 2))
        self.pull_valid = np.zeros((S, N), bool)
        self.pull_parent = np.full((S, N), -1, np.int64)
        self.pull_age = np.zeros((S, N), np.int64)
        self.graphs: list[GridGraph | None] = [None] * S
        self.dist_at = np.full(S, -1, np.int64)  # DART: the step an episode's disturbance starts
        self.dist_v = np.zeros((S, N, 2))  # ... and each robot's command offset while it lasts (random)
        self.dist_who = np.zeros(S, np.int64)  # ... or the robot pushed toward its nearest team-mate (approach)

    def reset(self, s: int, task: Task, ref: np.ndarray):
        self.q[s] = task.starts
        self.goal[s] = task.goal
        self.leader[s] = task.leader
        self.tree[s] = False
        self.has_tree[s] = False
        self.force_replan[s] = False
        self.prog[s] = self.best_prog[s] = self.stall[s] = self.t[s] = 0
        self.ref[s, :len(ref)] = ref
        self.ref[s, len(ref):] = ref[-1]
        self.ref_n[s] = len(ref)
        self.hist[s, 0] = task.starts
        self.v_prev[s] = 0.0
        self.pull_valid[s] = False
        self.pull_parent[s] = -1
        self.pull_age[s] = 0
