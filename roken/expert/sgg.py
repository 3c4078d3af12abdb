"""SGG (Shi et al. 2021, communication-aware multi-robot coordination), the paper's first baseline, batched.

No public code exists; this follows the paper's description ("discrete topology optimization with continuous
refinement", Related Work and Baselines) and the original's structure. Per decision step and team:
  1. the leader moves one full step toward the look-ahead point of its smoothed A* reference (the paper: every
     baseline's leader follows A*), or the evenly sampled candidate nearest that point when the step would come
     too close to an obstacle (a slide along the wall):
     it does not wait for the team (the followers make way and follow; when they cannot, the team disconnects,
     SGG's failure in the paper: connected 0.505 at reach 0.976);
  2. candidates: staying, and `directions` positions evenly around each robot on each of `rings` circles
     (k / rings of a full step);
  3. discrete topology search: the minimum spanning tree of the current positions (links <= R), rooted at the
     leader, is the minimal topology to keep; robots are placed in breadth-first order, each taking its
     cheapest candidate (motion, plus `cohesion` per metre beyond `comfort` from its parent's next position)
     that keeps obstacle clearance, spacing to every robot (placed ones at their next positions, the others
     where they are) and the link to its parent within R - comm_margin. A robot with no feasible candidate
     takes its safe candidate with the shortest link (the team may disconnect: the local minima the paper
     reports for SGG), and the step counts as one where the search found no feasible topology;
  4. continuous refinement: one L-BFGS-B problem (scipy.optimize) over every team's followers, minimising
     the distance to the discrete choice plus `refine_motion` x the motion and squared hinges on clearance (the
     map's bilinear SDF), spacing and the tree links (the discrete choice moved continuously to where the
     constraints hold with less motion), each coordinate boxed to a full step; a team whose refined positions
     break a hard constraint takes its discrete choice.
An episode ends when the leader is within eps_goal of its goal, or at the expert's step limit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from ..world.geometry import bilinear, clearance
from ..world.graph import connected, minimum_spanning_tree, tree_parents
from ..world.grid import GridMap
from ..world.tasks import Task, TaskConfig
from .laplacian import ExpertConfig, LaplacianExpert, advance_reference


@dataclass
class SGGConfig:
    directions: int = 8  # candidate headings around each robot
    rings: int = 2  # candidate step lengths: k / rings of a full step, k = 1..rings (and staying)
    margin_obs: float = 0.1  # m on top of d_obs_min for a candidate
    margin_coll: float = 0.1  # m on top of d_coll_min
    comm_margin: float = 2.0  # a tree link is kept within R - comm_margin
    comfort: float = 5.0  # m from the parent beyond which a follower's candidate pays `cohesion` per metre
    cohesion: float = 2.0  # > 1: a follower beyond `comfort` closes in (motion costs 1 per metre)
    refine: bool = True  # the continuous refinement (step 4)
    refine_iters: int = 15  # L-BFGS-B iterations per decision step
    refine_weight: float = 100.0  # weight of the constraint hinges against the distance to the discrete choice
    refine_motion: float = 0.2  # weight of the motion cost (distance to the current position), same units
    batch_size: int = 64


def team_feasible(q_new: np.ndarray, padded: np.ndarray, tc: TaskConfig) -> np.ndarray:
    """(S,) whether each team's positions (S, N, 2) keep every hard constraint: clearance >= d_obs_min,
    spacing >= d_coll_min, connected within R."""
    S, N, _ = q_new.shape
    clr = clearance(padded, q_new, np.broadcast_to(np.arange(S)[:, None], (S, N)))
    d = np.linalg.norm(q_new[:, :, None] - q_new[:, None], axis=-1) + np.eye(N)[None] * 1e9
    return (clr >= tc.d_obs_min).all(1) & (d >= tc.d_coll_min).all((1, 2)) & connected(d, tc.comm_radius)


class SGGPlanner:
    """Runs tasks of one team size; the same interface as LaplacianExpert.run (positions per episode)."""

    def __init__(self, cfg: SGGConfig, task_cfg: TaskConfig, expert_cfg: ExpertConfig | None = None):
        self.cfg, self.tc = cfg, task_cfg
        self.expert = LaplacianExpert(expert_cfg or ExpertConfig(), task_cfg)  # references and step limits
        ang = 2 * np.pi * np.arange(cfg.directions) / cfg.directions
        rings = [(k + 1) / cfg.rings * task_cfg.max_step * (1 - 1e-4) for k in range(cfg.rings)]
        self.offsets = np.concatenate([np.zeros((1, 2))] + [r * np.stack([np.cos(ang), np.sin(ang)], 1)
                                                             for r in rings])  # (K, 2), staying first
        self.step_len = np.linalg.norm(self.offsets, axis=1)  # (K,) each candidate's motion

    # ------------------------------------------------------------------ one decision step
    def _place(self, q, lead_next, parents, order, padded, clr_now, d_now):
        """Step 3 for every team: (next positions (S, N, 2), team feasible (S,)); d_now (S, N, N) the current
        pairwise distances."""
        cfg, tc = self.cfg, self.tc
        S, N, _ = q.shape
        sl = np.arange(S)
        nxt, placed = q.copy(), np.zeros((S, N), bool)
        leader = order[:, 0]
        nxt[sl, leader], placed[sl, leader] = lead_next, True
        ok_team = np.ones(S, bool)
        thr_obs, thr_coll = tc.d_obs_min + cfg.margin_obs, tc.d_coll_min + cfg.margin_coll
        for k in range(1, N):
            r = order[:, k]
            par = parents[sl, r]
            lost = par < 0  # outside the tree (a disconnected team): the nearest placed robot
            if lost.any():
                dp = np.where(placed[lost], np.linalg.norm(q[lost] - q[sl[lost], r[lost]][:, None], axis=-1), np.inf)
                par = par.copy()
                par[lost] = dp.argmin(1)
            cand = q[sl, r][:, None] + self.offsets[None]  # (S, K, 2)
            K = cand.shape[1]
            clr = clearance(padded, cand, np.broadcast_to(sl[:, None], (S, K)))
            ok_obs = (clr >= thr_obs) | (clr >= clr_now[sl, r][:, None])
            d = np.linalg.norm(cand[:, :, None] - nxt[:, None], axis=-1)  # (S, K, N): others where they will be
            other = np.arange(N)[None] != r[:, None]  # (S, N)
            ok_coll = (((d >= thr_coll) | (d >= d_now[sl, r][:, None])) | ~other[:, None]).all(2)
            link = np.linalg.norm(cand - nxt[sl, par][:, None], axis=-1)  # (S, K)
            ok_link = link <= tc.comm_radius - cfg.comm_margin
            cost = self.step_len[None] + cfg.cohesion * np.maximum(link - cfg.comfort, 0)
            feas = ok_obs & ok_coll & ok_link
            safe = ok_obs & ok_coll
            safe[:, 0] |= ~safe.any(1)  # nothing safe: stay
            pick = np.where(feas.any(1), np.where(feas, cost, np.inf).argmin(1), np.where(safe, link, np.inf).argmin(1))
            ok_team &= feas.any(1)
            nxt[sl, r], placed[sl, r] = cand[sl, pick], True
        return nxt, ok_team

    def _refine(self, q, nxt, leader, parents, sdf, active):
        """Step 4: one L-BFGS-B problem over every active team's followers."""
        cfg, tc = self.cfg, self.tc
        S, N, _ = q.shape
        sl = np.arange(S)
        move = np.ones((S, N), bool)
        move[sl, leader] = False
        move &= active[:, None]
        if not move.any():
            return nxt
        lo = np.where(move[..., None], q - tc.max_step, nxt).ravel()
        hi = np.where(move[..., None], q + tc.max_step, nxt).ravel()
        a_obs, a_coll = tc.d_obs_min + cfg.margin_obs, tc.d_coll_min + cfg.margin_coll
        radius = tc.comm_radius - cfg.comm_margin
        idx = np.broadcast_to(sl[:, None], (S, N))
        child = parents >= 0
        cb, cr = np.nonzero(child)
        cp = parents[cb, cr]
        pair = (np.triu(np.ones((N, N), bool), 1)[None] & active[:, None, None])
        W = cfg.refine_weight

        def fg(x):
            x = x.reshape(S, N, 2)
            dq, dn = x - q, x - nxt
            f = cfg.refine_motion * (dq ** 2).sum() + (dn ** 2).sum()
            g = 2 * cfg.refine_motion * dq + 2 * dn
            val, gs = bilinear(sdf, x, idx, with_grad=True)
            h = np.maximum(a_obs - val, 0) * active[:, None]
            f += W * (h ** 2).sum()
            g -= 2 * W * h[..., None] * gs
            diff = x[:, :, None] - x[:, None]
            dist = np.sqrt((diff ** 2).sum(-1) + 1e-12)
            h = np.maximum(a_coll - dist, 0) * pair
            f += W * (h ** 2).sum()
            gc = (2 * W * h / dist)[..., None] * diff  # on i, minus on j
            g -= gc.sum(2) - gc.sum(1)
            e = x[cb, cr] - x[cb, cp]
            de = np.sqrt((e ** 2).sum(-1) + 1e-12)
            h = np.maximum(de - radius, 0) * active[cb]
            f += W * (h ** 2).sum()
            ge = (2 * W * h / de)[:, None] * e
            np.add.at(g, (cb, cr), ge)
            np.add.at(g, (cb, cp), -ge)
            return f, (g * move[..., None]).ravel()

        res = minimize(fg, nxt.ravel(), jac=True, method="L-BFGS-B", bounds=list(zip(lo, hi)),
                       options={"maxiter": cfg.refine_iters})
        x = res.x.reshape(S, N, 2)
        step = x - q
        n = np.linalg.norm(step, axis=-1, keepdims=True)
        return q + step * np.minimum(1.0, tc.max_step * (1 - 1e-4) / np.maximum(n, 1e-12))

    # ------------------------------------------------------------------ main loop
    def run(self, tasks: list[Task], maps: dict[str, GridMap]):
        """Yield (task index, positions (T+1, N, 2) float32, info) as episodes finish (not in task order);
        info["feasible"] (T,) bool: whether the candidate search found a feasible topology at each step."""
        if not tasks:
            return
        N = tasks[0].num_robots
        if any(t.num_robots != N for t in tasks):
            raise ValueError("SGGPlanner.run takes tasks of one team size; group them first")
        cfg, tc = self.cfg, self.tc
        S = min(cfg.batch_size, len(tasks))
        shape = maps[tasks[0].map_id].shape
        prepared = [self.expert.prepare(t, maps[t.map_id]) for t in tasks]
        cap = max(len(p[0]) for p in prepared)
        sdf = np.zeros((S,) + shape, np.float32)
        padded = np.zeros((S,) + maps[tasks[0].map_id].padded.shape, bool)
        q, goal = np.zeros((S, N, 2)), np.zeros((S, 2))
        leader, prog, t, limit = (np.zeros(S, np.int64) for _ in range(4))
        ref, ref_n = np.zeros((S, cap, 2)), np.ones(S, np.int64)
        slot_task, hist, feas_hist = np.full(S, -1), [[] for _ in range(S)], [[] for _ in range(S)]
        pending = list(range(len(tasks)))[::-1]
        sl = np.arange(S)

        def fill(s):
            i = pending.pop()
            task, gm = tasks[i], maps[tasks[i].map_id]
            if gm.shape != shape:
                raise ValueError(f"map {gm.map_id} is {gm.shape}, expected {shape}: fit maps to the canvas")
            r, _, lim = prepared[i]
            sdf[s], padded[s] = gm.sdf, gm.padded
            q[s], goal[s], leader[s] = task.starts, task.goal, task.leader
            ref[s, :len(r)], ref[s, len(r):], ref_n[s] = r, r[-1], len(r)
            prog[s], t[s], limit[s], slot_task[s] = 0, 0, lim, i
            hist[s], feas_hist[s] = [q[s].copy()], []

        for s in range(S):
            fill(s)
        active = np.ones(S, bool)
        idx = np.broadcast_to(sl[:, None], (S, N))
        while active.any():
            lq = q[sl, leader]
            prog[:], target = advance_reference(ref, ref_n, prog, lq, self.expert.cfg.lookahead, tc.max_step)
            to = target - lq
            dist = np.linalg.norm(to, axis=-1, keepdims=True)
            lead_move = to / np.maximum(dist, 1e-9) * np.minimum(dist, tc.max_step * (1 - 1e-4))
            clr_now = clearance(padded, q, idx)
            d = np.linalg.norm(q[:, :, None] - q[:, None], axis=-1)
            tree = minimum_spanning_tree(np.where((d <= tc.comm_radius) & ~np.eye(N, dtype=bool)[None], d, np.inf))
            parents = tree_parents(tree, leader)
            depth = np.zeros((S, N), np.int64)
            for _ in range(N):  # hops to the leader; robots outside the tree last
                depth = np.where(parents >= 0, np.take_along_axis(depth, np.maximum(parents, 0), 1) + 1, depth)
            depth = np.where((parents < 0) & (np.arange(N)[None] != leader[:, None]), N + 1, depth)
            order = np.argsort(depth, axis=1, kind="stable")
            # the leader keeps to its reference: the safe candidate (its full step, or one of the evenly sampled
            # ones, which slide it along a wall) closest to the look-ahead point
            cand = np.concatenate([(lq + lead_move)[:, None], lq[:, None] + self.offsets[None]], 1)  # (S, 1+K, 2)
            c = clearance(padded, cand, np.broadcast_to(sl[:, None], cand.shape[:2]))
            ok = (c >= tc.d_obs_min + cfg.margin_obs) | (c >= clr_now[sl, leader][:, None])
            ok[:, 1] = True  # staying
            ln = cand[sl, np.where(ok, np.linalg.norm(cand - target[:, None], axis=-1), np.inf).argmin(1)]
            nxt, feasible = self._place(q, ln, parents, order, padded, clr_now, d)
            if cfg.refine:
                ref_pos = self._refine(q, nxt, leader, parents, sdf, active)
                keep = team_feasible(ref_pos, padded, tc)
                nxt = np.where(keep[:, None, None], ref_pos, nxt)
            nxt[~active] = q[~active]
            q[:] = nxt
            t += active
            reached = np.linalg.norm(q[sl, leader] - goal, axis=-1) <= tc.eps_goal * 0.9
            for s in np.nonzero(active)[0]:
                hist[s].append(q[s].copy())
                feas_hist[s].append(bool(feasible[s]))
                if reached[s] or t[s] >= limit[s]:
                    yield int(slot_task[s]), np.asarray(hist[s], np.float32), {"feasible": np.array(feas_hist[s])}
                    if pending:
                        fill(s)
                    else:
                        active[s] = False
