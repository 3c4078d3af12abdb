"""Constraint-guided sampling (`roken+guided`; beyond the paper, in the spirit of MPD / MMD cost guidance).

During the last `plan.guide_steps` DDIM steps, the predicted clean chunk is moved down the gradient of a cost
that uses only what a deployed planner has (its known map and its goal), then the sampler goes on from it:

  obstacle   sum_h w_h ReLU(d_obs_min + margin - sdf(p_ih))^2       bilinear SDF of the known map (metres)
  inter      sum_h w_h ReLU(d_coll_min + margin - |p_ih - p_jh|)^2  every pair, given robots included
  connect    sum_h w_h ReLU(|p_ih - p_jh| - (R - margin))^2         over the edges of each instant's minimum
                                                                     spanning tree (a connected team needs them)
  goal       mean_h geo(p_leader,h)                                 free-space (octile) distance to the goal on
                                                                     the known map, so the pull goes around blocks
w_h = guide_exec_weight for the executed moves (h < replan_every), 1 for the others. The descent runs on the
positions in metres (`guide_iters` steps of `guide_lr`, each point's update clipped to 0.25 m), given robots
(conditional mode, clustered rollout) never move, and the chunk is re-encoded with every move clipped to the
chunk's full-speed scale. Everything is batched over the episodes and candidates of a re-plan.
"""
from __future__ import annotations

import numpy as np
import torch

from ..data.samples import SampleConfig
from ..model.losses import decode_chunk, sdf_at
from ..world.geometry import signed_distance_field
from .select import geodesic_field


def mst_edges(dist: torch.Tensor, real: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Prim's algorithm on M small graphs at once: dist (M, N, N) (no gradient needed), real (M, N) bool.
    Returns (i, j) (M, N-1) node indices of the tree edges; edges of graphs with fewer real nodes repeat a
    self-edge (length 0)."""
    M, N, _ = dist.shape
    big = torch.finfo(dist.dtype).max / 4
    first = real.float().argmax(1)  # (M,) a real node to grow from
    in_tree = ~real.clone()
    in_tree[torch.arange(M), first] = True
    src_ok = real.clone()
    d = dist.masked_fill(~src_ok[:, :, None], big)
    ii, jj = [], []
    for _ in range(N - 1):
        cand = d.masked_fill(~(in_tree & real)[:, :, None] | in_tree[:, None, :], big)  # tree -> outside
        flat = cand.view(M, -1).argmin(1)
        i, j = flat // N, flat % N
        none = cand.view(M, -1).gather(1, flat[:, None])[:, 0] >= big  # nothing left to add
        i, j = torch.where(none, first, i), torch.where(none, first, j)
        in_tree[torch.arange(M), j] = True
        ii.append(i)
        jj.append(j)
    return torch.stack(ii, 1), torch.stack(jj, 1)


class Guide:
    """The cost of one re-plan's prompts and its descent; call it on predicted clean chunks (B G, R, H, 2)."""

    def __init__(self, pc, tc, samples: SampleConfig, start: np.ndarray, real: np.ndarray, generated: np.ndarray,
                 leader: np.ndarray, sdf: np.ndarray, geo: np.ndarray, G: int, device="cpu"):
        # start (B, R, 2) m, real / generated (B, R) bool, leader (B,) token index or -1, sdf / geo (B, S, S)
        t = lambda a, dt=torch.float32: torch.as_tensor(np.asarray(a), dtype=dt, device=device).repeat_interleave(G, 0)  # noqa: E731
        self.pc, self.tc, self.samples = pc, tc, samples
        self.start, self.real, self.gen = t(start), t(real, torch.bool), t(generated, torch.bool)
        self.leader = t(leader, torch.long)
        self.sdf, self.geo = t(sdf), t(geo)

    def cost(self, p: torch.Tensor) -> torch.Tensor:
        """p (B, R, H, 2) metres -> (B,) guidance cost."""
        pc, tc = self.pc, self.tc
        B, R, H, _ = p.shape
        w = torch.ones(H, device=p.device)
        w[:pc.replan_every] = pc.guide_exec_weight
        real = self.real.float()
        m = pc.guide_margin
        total = torch.zeros(B, device=p.device)
        if pc.guide_obstacle > 0:
            pen = torch.relu(tc.d_obs_min + m - sdf_at(self.sdf, p)) ** 2  # (B, R, H)
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
                i, j = mst_edges(flat.detach(), self.real.repeat_interleave(H, 0))
                e = flat[torch.arange(B * H, device=p.device)[:, None], i, j]  # (B H, R-1)
                pen = torch.relu(e - (tc.comm_radius - m)) ** 2
                total = total + pc.guide_connect * (pen.sum(1).view(B, H) * w).sum(1)
        if pc.guide_goal > 0:  # every point of the leader's chunk, so that the executed moves feel the pull too
            has = self.leader >= 0
            lead = p[torch.arange(B, device=p.device), self.leader.clamp(min=0)]  # (B, H, 2)
            g = sdf_at(self.geo, lead).mean(1)
            total = total + pc.guide_goal * torch.where(has, g, torch.zeros_like(g))
        return total

    @torch.enable_grad()
    def __call__(self, x0: torch.Tensor, given: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        """x0, given (B, R, H, 2) normalised chunks, fixed (B, R, 1, 1) bool -> the guided clean chunk."""
        sc, pc = self.samples, self.pc
        x0 = torch.where(fixed, given, x0).float()
        p0 = decode_chunk(x0, self.start, sc).detach()
        p = p0.clone().requires_grad_(True)
        move = self.gen[:, :, None, None].float()
        for _ in range(pc.guide_iters):
            c = self.cost(p).sum()
            (grad,) = torch.autograd.grad(c, p)
            step = pc.guide_scale * pc.guide_lr * grad * move
            n = step.norm(dim=-1, keepdim=True)
            step = step * torch.clamp(0.25 / n.clamp(min=1e-9), max=1.0)  # at most 0.25 m per point and step
            with torch.no_grad():
                p -= step
        p = p.detach()
        if sc.representation == "relative":
            prev = torch.cat([self.start[:, :, None], p[:, :, :-1]], 2)
            chunk = (p - prev) / sc.step_scale
            n = chunk.norm(dim=-1, keepdim=True)
            chunk = chunk * torch.clamp(1.0 / n.clamp(min=1e-9), max=1.0)  # never faster than full speed
        else:
            chunk = p / sc.pos_scale - 1.0
        return torch.where(fixed, given, chunk.to(given.dtype))


def known_fields(known_occupancy: np.ndarray, goal, graph=None) -> tuple[np.ndarray, np.ndarray]:
    """The SDF and the finite geodesic field (unknown / unreachable: the largest distance + 20 m) of a known map."""
    sdf = signed_distance_field(known_occupancy)
    if goal is None:
        return sdf, np.zeros_like(sdf)
    geo = geodesic_field(known_occupancy, np.asarray(goal, np.float64), graph)
    finite = np.isfinite(geo)
    top = float(geo[finite].max()) if finite.any() else 0.0
    return sdf, np.where(finite, geo, top + 20.0).astype(np.float32)
