"""Constraint-guided sampling (`roken+guided`; beyond the paper, in the spirit of MPD / MMD cost guidance).

During the last `plan.guide_steps` DDIM steps, the predicted clean chunk is moved down the gradient of a cost
that uses only what a deployed planner has (its known map and its goal), then the sampler goes on from it:

  obstacle   sum_h w_h ReLU(d_obs_min + margin - sdf(p_ih))^2       bilinear SDF of the known map (metres)
  inter      sum_h w_h ReLU(d_coll_min + margin - |p_ih - p_jh|)^2  every pair, given robots included, and
                                                                     every robot against the team's robots
                                                                     outside the prompt (clustered rollout:
                                                                     earlier clusters' plans, later clusters'
                                                                     robots where they stand, `outside`)
  connect    sum_h w_h ReLU(|p_ih - p_jh| - (R - margin))^2         over the edges of each instant's minimum
                                                                     spanning tree (a connected team needs them)
  goal       mean_h geo(p_leader,h)                                 free-space (octile) distance to the goal on
                                                                     the known map, so the pull goes around blocks
  follow     sum_h w_h ReLU(lead(p_ih) - r) / H                     each generated follower's free-space distance
                                                                     to the leader's current position beyond
                                                                     r = guide_follow_range: a stalled follower
                                                                     tethers the whole chain (off by default)
w_h = guide_exec_weight for the executed moves (h < replan_every), 1 for the others. The descent runs on the
positions in metres (`guide_iters` steps of `guide_lr` at each guided DDIM step, `guide_final_iters` at the last
one; each point's update clipped to 0.25 m), given robots (conditional mode, clustered rollout) never move, and
the chunk is re-encoded with every move clipped to the chunk's full-speed scale. Everything is batched over the
episodes and candidates of a re-plan.

Speed: the arrays are tiny (B G rows of R x 16 points), so an iteration costs what its number of array calls
costs. The descent therefore runs in numpy on the host with the cost's gradient in closed form (`Guide.grad`:
the bilinear fields' exact gradients, the pair terms from the pair differences) instead of torch autograd
through `Guide.cost`, which stays as the differentiable reference the tests check `grad` against; the spanning
trees are re-grown every `MST_EVERY` iterations rather than every one (a tree changes only when the team's
shape does). Figures: benchmarks/README.md.
"""
from __future__ import annotations

import numpy as np
import torch

from ..data.samples import SampleConfig
from ..model.losses import decode_chunk, sdf_at
from ..world.geometry import bilinear, signed_distance_field
from .select import geodesic_field

MST_EVERY = 10  # descent iterations between re-grown spanning trees


def field_and_grad(field: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bilinear value of cell-centred fields (B, S, S) at pts (B, ..., 2) metres and its gradient (B, ..., 2),
    as losses.sdf_at interpolates (grid_sample, align_corners=False, border: no gradient outside the centres)."""
    index = np.broadcast_to(np.arange(len(field)).reshape((-1,) + (1,) * (pts.ndim - 2)), pts.shape[:-1])
    # float64: bilinear clips to S - 1 - 1e-6, which float32 rounds to S - 1 (a row past the field's end)
    val, g = bilinear(field, pts.astype(np.float64), index, with_grad=True)
    S = field.shape[-1]
    return val, g * ((pts > 0.5) & (pts < S - 0.5))


def mst_edges(dist: np.ndarray, real: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Prim's algorithm on M small graphs at once: dist (M, N, N), real (M, N) bool. Returns (i, j) (M, N-1)
    node indices of the tree edges; edges of graphs with fewer real nodes repeat a self-edge (length 0)."""
    M, N, _ = dist.shape
    big = np.inf
    rows = np.arange(M)
    first = real.argmax(1)  # (M,) a real node to grow from
    in_tree = ~real.copy()
    in_tree[rows, first] = True
    d = np.where(real[:, :, None], dist, big)
    ii, jj = [], []
    for _ in range(N - 1):
        cand = np.where((in_tree & real)[:, :, None] & ~in_tree[:, None, :], d, big).reshape(M, -1)  # tree -> out
        flat = cand.argmin(1)
        i, j = flat // N, flat % N
        none = ~np.isfinite(cand[rows, flat])  # nothing left to add
        i, j = np.where(none, first, i), np.where(none, first, j)
        in_tree[rows, j] = True
        ii.append(i)
        jj.append(j)
    return np.stack(ii, 1), np.stack(jj, 1)


class Guide:
    """The cost of one re-plan's prompts and its descent; call it on predicted clean chunks (B G, R, H, 2)."""

    def __init__(self, pc, tc, samples: SampleConfig, start: np.ndarray, real: np.ndarray, generated: np.ndarray,
                 leader: np.ndarray, sdf: np.ndarray, geo: np.ndarray, G: int, device="cpu",
                 lead: np.ndarray | None = None, outside: tuple[np.ndarray, np.ndarray] | None = None):
        # start (B, R, 2) m, real / generated (B, R) bool, leader (B,) token index or -1, sdf / geo (B, S, S);
        # lead (B, S, S): free-space distance to the team leader's position (the follow term; None = off);
        # outside: (points (B, K, H, 2) m, weights (B, K, H)) of team robots that are not in the prompt, which
        # its robots must not come near (the inter-robot hinge, one-sided: they never move); None = none
        rep = lambda a, dt=np.float32: np.repeat(np.asarray(a, dt), G, 0)  # noqa: E731
        self.pc, self.tc, self.samples, self.device = pc, tc, samples, torch.device(device)
        # the descent runs in numpy on the host: its arrays are tiny, so a torch call's dispatch would dominate
        self.real, self.gen, self.leader = rep(real, bool), rep(generated, bool), rep(leader, np.int64)
        self.sdf, self.geo = rep(sdf), rep(geo)  # (B G, S, S)
        self.lead = rep(lead) if lead is not None and pc.guide_follow > 0 else None
        self.start = torch.as_tensor(rep(start), device=self.device)
        # what does not change along the descent: the move weights of every robot and of every robot pair
        w, real_f = self.weights(samples.horizon), self.real.astype(np.float32)
        R = real_f.shape[1]
        self._wreal = w * real_f[:, :, None]  # (B G, R, H)
        self._pairw = (real_f[:, :, None] * real_f[:, None] * (1 - np.eye(R, dtype=np.float32)))[..., None] * w
        follower = self.gen & (np.arange(R)[None] != self.leader[:, None])  # generated robots, not the leader
        self._wfollow = w * follower[:, :, None].astype(np.float32) / len(w)  # (B G, R, H)
        self.out_pts = self._wout = None
        if outside is not None and outside[0].shape[1] > 0 and pc.guide_inter > 0:
            self.out_pts = rep(outside[0])[:, None]  # (B G, 1, K, H, 2)
            self._wout = rep(outside[1])[:, None] * w * real_f[:, :, None, None]  # (B G, R, K, H)

    def weights(self, H: int) -> np.ndarray:
        w = np.ones(H, np.float32)
        w[:self.pc.replan_every] = self.pc.guide_exec_weight
        return w

    def cost(self, p: torch.Tensor) -> torch.Tensor:
        """p (B, R, H, 2) metres -> (B,) guidance cost, in torch (differentiable): the reference `grad` is
        checked against."""
        pc, tc = self.pc, self.tc
        B, R, H, _ = p.shape
        t = lambda a: torch.as_tensor(a, device=p.device)  # noqa: E731
        w, real, m = t(self.weights(H)), t(self.real).float(), pc.guide_margin
        total = torch.zeros(B, device=p.device)
        if pc.guide_obstacle > 0:
            pen = torch.relu(tc.d_obs_min + m - sdf_at(t(self.sdf), p)) ** 2  # (B, R, H)
            total = total + pc.guide_obstacle * (pen * w * real[:, :, None]).sum((1, 2))
        if R > 1 and (pc.guide_inter > 0 or pc.guide_connect > 0):
            q = p.transpose(1, 2)  # (B, H, R, 2)
            d = (q[:, :, :, None] - q[:, :, None]).pow(2).sum(-1).add(1e-9).sqrt()  # (B, H, R, R)
            pair = (real[:, None, :, None] * real[:, None, None, :]).expand(B, H, R, R)
            if pc.guide_inter > 0:
                off = 1 - torch.eye(R, device=p.device)
                pen = torch.relu(tc.d_coll_min + m - d) ** 2 * pair * off / 2
                total = total + pc.guide_inter * (pen.sum((2, 3)) * w).sum(1)
            if pc.guide_connect > 0:
                flat = d.reshape(B * H, R, R)
                i, j = map(t, mst_edges(flat.detach().cpu().numpy(), np.repeat(self.real, H, 0)))
                e = flat[torch.arange(B * H, device=p.device)[:, None], i, j]  # (B H, R-1)
                pen = torch.relu(e - (tc.comm_radius - m)) ** 2
                total = total + pc.guide_connect * (pen.sum(1).view(B, H) * w).sum(1)
        if self.out_pts is not None:
            d = (p[:, :, None] - t(self.out_pts)).pow(2).sum(-1).add(1e-9).sqrt()  # (B, R, K, H)
            pen = torch.relu(tc.d_coll_min + m - d) ** 2 * t(self._wout)
            total = total + pc.guide_inter * pen.sum((1, 2, 3))
        if pc.guide_goal > 0:  # every point of the leader's chunk, so that the executed moves feel the pull too
            has = t(self.leader >= 0)
            lead = p[torch.arange(B, device=p.device), t(self.leader).clamp(min=0)]  # (B, H, 2)
            g = sdf_at(t(self.geo), lead).mean(1)
            total = total + pc.guide_goal * torch.where(has, g, torch.zeros_like(g))
        if self.lead is not None:
            pen = torch.relu(sdf_at(t(self.lead), p) - pc.guide_follow_range)  # (B, R, H)
            total = total + pc.guide_follow * (pen * t(self._wfollow)).sum((1, 2))
        return total

    def trees(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each instant's minimum spanning tree of the real robots, p (B, R, H, 2) -> the tree edges as flat
        point indices into p.reshape(-1, 2), (i, j), and each edge's move weight w_h (B H (R-1),)."""
        B, R, H, _ = p.shape
        q = p.transpose(0, 2, 1, 3)  # (B, H, R, 2)
        d = np.sqrt(((q[:, :, :, None] - q[:, :, None]) ** 2).sum(-1)).reshape(B * H, R, R)
        i, j = mst_edges(d, np.repeat(self.real, H, 0))  # (B H, R-1) robot indices
        bh = np.arange(B * H)[:, None]
        b, h = bh // H, bh % H
        w = np.broadcast_to(self.weights(H)[h], i.shape)
        return ((b * R + i) * H + h).ravel(), ((b * R + j) * H + h).ravel(), w.ravel()

    def grad(self, p: np.ndarray, edges: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """d cost / d p in closed form, p (B, R, H, 2) metres (numpy) -> (B, R, H, 2); `edges`: the spanning
        trees (from `trees`) of the connectivity term, grown from p when not given (as the reference does)."""
        pc, tc = self.pc, self.tc
        B, R, H, _ = p.shape
        m = pc.guide_margin
        rows, lead = np.arange(B), np.maximum(self.leader, 0)
        g = np.zeros_like(p)
        if pc.guide_goal > 0:
            _, gg = field_and_grad(self.geo, p[rows, lead])  # (B, H, 2)
            g[rows, lead] = (pc.guide_goal / H) * gg * (self.leader >= 0)[:, None, None]
        if self.lead is not None:
            val, gl = field_and_grad(self.lead, p)  # (B, R, H), (B, R, H, 2)
            g += pc.guide_follow * ((val > pc.guide_follow_range) * self._wfollow)[..., None] * gl
        if pc.guide_obstacle > 0:
            val, gs = field_and_grad(self.sdf, p)  # (B, R, H), (B, R, H, 2)
            v = np.maximum(tc.d_obs_min + m - val, 0) * self._wreal
            g -= (2 * pc.guide_obstacle) * v[..., None] * gs
        if R > 1 and pc.guide_inter > 0:
            diff = p[:, :, None] - p[:, None]  # (B, R, R, H, 2): p_i - p_j
            d = np.sqrt((diff ** 2).sum(-1) + 1e-9)  # (B, R, R, H)
            v = np.maximum(tc.d_coll_min + m - d, 0) * self._pairw  # (B, R, R, H)
            g -= (2 * pc.guide_inter) * ((v / d)[..., None] * diff).sum(2)
        if self.out_pts is not None:
            diff = p[:, :, None] - self.out_pts  # (B, R, K, H, 2)
            d = np.sqrt((diff ** 2).sum(-1) + 1e-9)
            v = np.maximum(tc.d_coll_min + m - d, 0) * self._wout
            g -= (2 * pc.guide_inter) * ((v / d)[..., None] * diff).sum(2)
        if R > 1 and pc.guide_connect > 0:
            i, j, we = edges if edges is not None else self.trees(p)
            pf = p.reshape(-1, 2)
            df = pf[i] - pf[j]  # (E, 2)
            e = np.sqrt((df ** 2).sum(-1) + 1e-9)
            ge = ((2 * pc.guide_connect) * np.maximum(e - (tc.comm_radius - m), 0) * we / e)[:, None] * df
            n = pf.shape[0]
            gn = np.stack([np.bincount(i, ge[:, c], n) - np.bincount(j, ge[:, c], n) for c in range(2)], -1)
            g += gn.reshape(p.shape).astype(p.dtype)
        return g

    @torch.no_grad()
    def __call__(self, x0: torch.Tensor, given: torch.Tensor, fixed: torch.Tensor, last: bool = True) -> torch.Tensor:
        """x0, given (B, R, H, 2) normalised chunks, fixed (B, R, 1, 1) bool -> the guided clean chunk;
        `last`: the final DDIM step (plan.guide_final_iters iterations, else plan.guide_iters)."""
        sc, pc = self.samples, self.pc
        x0 = torch.where(fixed, given, x0).float()
        p = decode_chunk(x0, self.start, sc).cpu().numpy()
        move = self.gen[:, :, None, None].astype(np.float32)
        iters = pc.guide_final_iters if last and pc.guide_final_iters > 0 else pc.guide_iters
        lr, edges = pc.guide_scale * pc.guide_lr, None
        for it in range(iters):
            if p.shape[1] > 1 and pc.guide_connect > 0 and it % MST_EVERY == 0:
                edges = self.trees(p)
            step = lr * self.grad(p, edges) * move
            n = np.sqrt((step ** 2).sum(-1, keepdims=True))
            p = p - step * np.minimum(0.25 / np.maximum(n, 1e-9), 1.0)  # at most 0.25 m per point and step
        p = torch.from_numpy(p).to(x0.device)
        if sc.representation == "relative":
            prev = torch.cat([self.start[:, :, None], p[:, :, :-1]], 2)
            chunk = (p - prev) / sc.step_scale
            n = chunk.norm(dim=-1, keepdim=True)
            chunk = chunk * torch.clamp(1.0 / n.clamp(min=1e-9), max=1.0)  # never faster than full speed
        else:
            chunk = p / sc.pos_scale - 1.0
        return torch.where(fixed, given, chunk.to(given.dtype))


def finite_geodesic(known_occupancy: np.ndarray, point, graph=None) -> np.ndarray:
    """(S, S) float32 free-space distance to `point` on a known map; unknown / unreachable cells: the largest
    distance + 20 m (a descent needs finite values)."""
    geo = geodesic_field(known_occupancy, np.asarray(point, np.float64), graph)
    finite = np.isfinite(geo)
    top = float(geo[finite].max()) if finite.any() else 0.0
    return np.where(finite, geo, top + 20.0).astype(np.float32)


def known_fields(known_occupancy: np.ndarray, goal, graph=None) -> tuple[np.ndarray, np.ndarray]:
    """The SDF and the finite geodesic field to the goal of a known map."""
    sdf = signed_distance_field(known_occupancy)
    if goal is None:
        return sdf, np.zeros_like(sdf)
    return sdf, finite_geodesic(known_occupancy, goal, graph)
