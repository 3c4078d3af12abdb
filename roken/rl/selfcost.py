"""The constraint cost of the model's own samples as a training term (`selfcost` section; beyond the paper).

Plain Roken fails because its samples break the hard constraints in states of its own making (README, "Handing
the start to the expert"), while the guided planner's samples deviate from the expert's as much and stay
feasible: what plain samples lack is deviations that respect the constraints. Losses on demonstrations cannot
teach that (the expert's chunks already respect them: `loss.sep` measured 0.0005 on them), and guidance fixes it
only at plan time. This term puts the guidance's cost (roken/plan/guidance.py: obstacle clearance, inter-robot
separation, connectivity of each instant's spanning tree, the leader's free-space distance to the goal) on what
the model itself samples, in the states its closed-loop rollouts visited, and back-propagates it into the
weights, in the manner of reward fine-tuning through the sampler (DRaFT, Clark et al. 2023; AlignProp): each
optimizer step draws `prompts` visited states x `candidates` noises, runs DDIM without gradients to one of the
`grad_steps` steps before the last, and differentiates the cost of that step's predicted clean chunk (truncated
back-propagation: one model call carries the gradient; late in a deterministic DDIM chain the predicted clean
chunk is the sample the planner will return, give or take the last steps' small corrections). The expert's
denoising loss stays beside it as the anchor that keeps the model an imitation of the expert.

States come from evaluation folders of rollouts on `train` maps (`pipelines/evaluate.py --maps train`, or the
`rollouts/` of DAgger rounds): every `state_every` simulator steps up to the first violation (the feasible states
the model must leave feasibly), each with its last chunk move (`model.prev_move`).

`distil` (a weight beside `weight`, or instead of it) distils the guided sampler rather than descending its cost
(guidance distillation, as Meng et al. 2023 distil classifier-free guidance): from the same noise, the planner's
constraint-guided DDIM (the `plan` section's guidance, as `roken+guided` samples) gives the target, and the graded
step's predicted clean chunk is regressed onto it (mean square over the real robots' points, in chunk units). The
target is a small, feasible correction of the model's own sample, so the pull has no speed to trade for safety
(the guided planner keeps the leader at its pace) and does not drift far from what the model already does; targets
whose executed moves still break a constraint are dropped.

`pace` turns the goal term into a hinge: only a leader that falls behind `pace` metres per simulator step along
the free-space distance is pulled, so a leader on schedule is left to the constraint terms (a constant pull keeps
rewarding speed beyond the expert's, which brings the violations back).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ..data.condition import build_condition
from ..data.samples import SampleConfig
from ..model.diffusion import COND_KEYS, NoiseSchedule, ddim_sample, ddim_steps, make_prompt, model_eps
from ..model.losses import decode_chunk, sdf_at
from ..plan.guidance import Guide, finite_geodesic
from ..plan.rollout import PlanConfig
from ..world.geometry import signed_distance_field
from ..world.tasks import TaskConfig


@dataclass
class SelfCostConfig:
    weight: float = 0.0  # the term's weight beside the denoising loss (0 = off)
    states: str = ""  # comma-separated evaluation folders of rollouts whose visited states are the prompts
    prompts: int = 8  # visited states per optimizer step
    candidates: int = 4  # noise draws per state
    steps: int = 10  # DDIM steps of the samples (the planner's plan.steps)
    grad_steps: int = 3  # the gradient flows through the predicted chunk of one of the grad_steps DDIM steps
    #                      before the last
    state_every: int = 8  # simulator steps between the states taken from a rollout
    # the leader's goal term's weight (the guidance's plan.guide_goal is 2): the constraint terms alone are
    # cheapest for a team that stands still; the pull keeps the leader moving, the anchor does the rest
    goal: float = 0.5
    # > 0: the goal term pulls only a leader that falls behind this pace (metres per simulator step along the
    # free-space distance; the expert's leader: 0.29 on data/val4): ReLU(geo(p_h) - (geo(start) - pace t_h)),
    # mean over the chunk, times `goal`. A constant pull keeps rewarding speed past the expert's, which buys the
    # violations back; a pace hinge leaves a leader on schedule to the constraint terms. 0 = the constant pull
    pace: float = 0.0
    # metres added to d_coll_min in the term's inter-robot hinge (the guidance's margin already adds plan.guide_margin):
    # plain rollouts' first violation is mostly a slow drift of one robot into a team-mate that the term left at the
    # hinge's edge, while the expert keeps pairs 3.1 m or more apart (10th percentile); 0 = the guidance's hinge
    spacing: float = 0.0
    # weight of the guided target: the sample regressed onto the guided sampler's chunk from the same noise (the
    # plan section's guidance, goal pull included, as `roken+guided` samples); 0 = off
    distil: float = 0.0
    seed: int = 0


def active(sc: SelfCostConfig) -> bool:
    """Whether the term is on: its cost part, its guided target, or both."""
    return sc.weight > 0 or sc.distil > 0


def check(sc: SelfCostConfig, need_states: bool = True) -> None:
    """need_states=False: the caller supplies them (DAgger: each round's rollouts)."""
    for k in ("weight", "distil", "pace", "spacing"):
        if getattr(sc, k) < 0:
            raise ValueError(f"selfcost.{k}={getattr(sc, k)}: must be >= 0 (0 = off)")
    if active(sc) and need_states and not sc.states.strip():
        raise ValueError("selfcost.weight > 0 (or selfcost.distil > 0) needs selfcost.states: evaluation folders of "
                         "closed-loop rollouts on train maps (pipelines/evaluate.py --maps train --out DIR, or a "
                         "DAgger round's rollouts/)")
    for k in ("prompts", "candidates", "steps", "grad_steps", "state_every"):
        if getattr(sc, k) < 1:
            raise ValueError(f"selfcost.{k}={getattr(sc, k)}: must be >= 1")


def visited_states(folders: list[str], tc: TaskConfig, every: int
                   ) -> tuple[dict, list[dict], list[tuple[int, int]]]:
    """The feasible states of the rollouts in `folders`: (maps by id, episodes, [(episode, t)]) with one state
    every `every` steps before each episode's first violation or the leader's arrival."""
    from ..dagger.relabel import feasible_span  # dagger sits above plan and rl; imported where it is used
    from ..data.store import read_run

    maps, episodes, states = {}, [], []
    for f in folders:
        m, eps = read_run(f)
        maps.update(m)
        episodes += eps
    for e, ep in enumerate(episodes):
        _, end = feasible_span(np.asarray(ep["positions"], np.float64), maps[ep["map_id"]],
                               np.asarray(ep["goal"], np.float64), int(ep["leader"]), tc)
        states += [(e, t) for t in range(0, end, every)]
    return maps, episodes, states


class SelfCost:
    """Call it with the model (training mode) at an optimizer step: (weighted loss, log figures)."""

    def __init__(self, sc: SelfCostConfig, samples: SampleConfig, pc: PlanConfig, tc: TaskConfig, rank: int = 0):
        check(sc)
        self.rank = rank  # Ray Train workers draw different states (their gradients are averaged)
        self.sc, self.samples, self.pc, self.tc = sc, samples, replace(pc, guide_goal=sc.goal, guide_follow=0.0), tc
        self.plan_pc = replace(pc, guide_follow=0.0)  # the guided target: the planner's guidance as it samples
        folders = [f.strip() for f in sc.states.split(",") if f.strip()]
        self.maps, self.episodes, self.states = visited_states(folders, tc, sc.state_every)
        if not self.states:
            raise ValueError(f"selfcost.states={sc.states!r}: no feasible state in its rollouts")
        self._fields: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # episode -> (SDF, free-space distance to goal)

    def fields(self, e: int) -> tuple[np.ndarray, np.ndarray]:
        if e not in self._fields:
            ep = self.episodes[e]
            occ = self.maps[ep["map_id"]].occupancy
            self._fields[e] = (signed_distance_field(occ), finite_geodesic(occ, np.asarray(ep["goal"], np.float64)))
        return self._fields[e]

    def prompts(self, rng: np.random.Generator) -> tuple[list[dict], list[int]]:
        """`prompts` visited states as model conditions, and their episodes."""
        conds, eps = [], []
        for i in rng.choice(len(self.states), self.sc.prompts, replace=len(self.states) < self.sc.prompts):
            e, t = self.states[i]
            ep = self.episodes[e]
            P = np.asarray(ep["positions"], np.float64)
            conds.append(build_condition(self.maps[ep["map_id"]].occupancy, P[t], int(ep["leader"]),
                                         np.asarray(ep["goal"], np.float64), self.samples,
                                         previous=P[max(0, t - self.samples.interval)]))
            eps.append(e)
        return conds, eps

    def __call__(self, model, sched: NoiseSchedule, step: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        sc, G = self.sc, self.sc.candidates
        # the step's draws (a resumed run repeats them), and each worker's own
        rng = np.random.default_rng([sc.seed, step] + ([self.rank] if self.rank else []))
        conds, eps = self.prompts(rng)
        dev = next(model.parameters()).device
        batch = {k: torch.from_numpy(np.stack([c[k] for c in conds])).to(dev) for k in COND_KEYS + ("map", "chunk")}
        prompt = make_prompt(model, {k: batch[k] for k in COND_KEYS + ("map",)}, batch["chunk"], G)
        gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        x_T = torch.randn(prompt.given.shape, generator=gen).to(dev)  # shared by the sample and its guided target
        seq = ddim_steps(sched.K, sc.steps)
        # the graded step: one of the grad_steps before the last (the last, k = 0, scales the noise prediction by
        # sqrt(1 - abar_0) ~ 0.01: its clean chunk hardly depends on the weights, so its gradient is nil)
        graded = max(len(seq) - 2 - int(rng.integers(min(sc.grad_steps, len(seq) - 1))), 0)
        # DDIM (eta = 0) to the graded step without gradients, as the planner samples; then one model call with them
        x = ddim_sample(model, sched, prompt, sc.steps, noise=lambda shape: x_T, stop=graded).chunk  # (B G, R, H, 2)
        ks = torch.full((x.shape[0],), seq[graded], device=dev, dtype=torch.long)
        x0 = sched.predict_x0(x, ks, model_eps(model, sched, prompt, x, ks))
        start = prompt.cond["start"]
        p = decode_chunk(x0, start, self.samples)  # (B G, R, H, 2) metres
        real = np.stack([c["robot_mask"] for c in conds])
        leader = np.array([int(np.argmax(c["goal_mask"])) for c in conds])
        sdf, geo = map(np.stack, zip(*(self.fields(e) for e in eps)))
        starts = np.stack([c["start"] for c in conds])
        sdf_t = torch.as_tensor(np.repeat(sdf, G, 0), device=dev)  # (B G, S, S)
        real_t = torch.as_tensor(np.repeat(real, G, 0), device=dev)  # (B G, R)
        h = self.pc.replan_every
        with torch.no_grad():  # how many of the sampled executed moves break a hard constraint
            viol = self.violating(p[:, :, :h].detach(), sdf_t, real_t)
        fields = (starts, real, leader, sdf, geo)
        loss, logs = x0.new_zeros(()), {"selfcost/violating": viol.float().mean()}
        if sc.distil > 0:
            err, bad = self.distilled(model, sched, prompt, x_T, x0, fields, sdf_t, real_t)
            loss = loss + sc.distil * err
            logs |= {"losses/distil": err.detach(), "selfcost/target_violating": bad}
        if sc.weight > 0:
            cost = self.costed(p, start, fields)
            loss = loss + sc.weight * cost.mean()
            logs["losses/selfcost"] = cost.mean().detach()
        return loss, logs

    def distilled(self, model, sched, prompt, x_T, x0, fields, sdf_t, real_t) -> tuple[torch.Tensor, torch.Tensor]:
        """The mean square distance (chunk units, real robots) of the predicted clean chunks x0 to the guided
        sampler's chunks from the same noise x_T, and the share of those targets dropped (their executed moves
        still break a constraint)."""
        starts, real, leader, sdf, geo = fields
        guide = Guide(self.plan_pc, self.tc, self.samples, starts, real, real, leader, sdf, geo, self.sc.candidates,
                      x0.device)
        target = ddim_sample(model, sched, prompt, self.sc.steps, noise=lambda shape: x_T, guide=guide,
                             guide_steps=self.plan_pc.guide_steps).chunk  # (B G, R, H, 2), no gradient
        with torch.no_grad():
            pts = decode_chunk(target, prompt.cond["start"], self.samples)[:, :, :self.pc.replan_every]
            keep = ~self.violating(pts, sdf_t, real_t)
            w = (real_t.float() * keep[:, None].float())[:, :, None, None]  # (B G, R, 1, 1)
        err = ((x0 - target) ** 2 * w).sum() / (w.sum() * x0.shape[2] * x0.shape[3]).clamp(min=1)
        return err, 1 - keep.float().mean()

    def costed(self, p: torch.Tensor, start: torch.Tensor, fields) -> torch.Tensor:
        """(B G,) the guidance's cost of the chunks p (metres), its goal term a pace hinge with selfcost.pace, its
        inter-robot hinge selfcost.spacing further out."""
        starts, real, leader, sdf, geo = fields
        pc = replace(self.pc, guide_goal=0.0) if self.sc.pace > 0 else self.pc
        tc = replace(self.tc, d_coll_min=self.tc.d_coll_min + self.sc.spacing)
        guide = Guide(pc, tc, self.samples, starts, real, real, leader, sdf, geo, self.sc.candidates, p.device)
        cost = guide.cost(p)
        if self.sc.pace > 0:  # the guide holds the fields and leaders repeated per candidate
            cost = cost + self.sc.goal * self.behind(p, start, torch.as_tensor(guide.geo, device=p.device),
                                                     torch.as_tensor(guide.leader, device=p.device))
        return cost

    def behind(self, p: torch.Tensor, start: torch.Tensor, geo: torch.Tensor, leader: torch.Tensor) -> torch.Tensor:
        """(B,) how far the leader's chunk points p (B, R, H, 2) m lag behind `selfcost.pace` along the free-space
        distance to the goal `geo` (B, S, S), mean over the chunk; start (B, R, 2) m, leader (B,) token index."""
        rows, H = torch.arange(len(p), device=p.device), p.shape[2]
        g = sdf_at(geo, p[rows, leader])  # (B, H) free-space distance of each leader point
        g0 = sdf_at(geo, start[rows, leader][:, None])  # (B, 1) ... of where it stands
        t = self.samples.interval * torch.arange(1, H + 1, device=p.device, dtype=p.dtype)  # simulator steps
        return torch.relu(g - (g0 - self.sc.pace * t).clamp(min=0)).mean(1)

    def violating(self, p: torch.Tensor, sdf: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
        """(B,) whether the points p (B, R, h, 2) come within d_obs_min of an obstacle or d_coll_min of each
        other, or leave a robot without a neighbour within the radius (a disconnected team's telltale)."""
        tc, r = self.tc, real.float()
        obs = ((sdf_at(sdf, p) < tc.d_obs_min).float() * r[:, :, None]).amax((1, 2)) > 0
        d = (p[:, :, None] - p[:, None]).norm(dim=-1)  # (B, R, R, h)
        pair = (r[:, :, None] * r[:, None] * (1 - torch.eye(r.shape[1], device=p.device)))[..., None] > 0
        inter = (pair & (d < tc.d_coll_min)).flatten(1).any(1)
        alone = ((pair & (d <= tc.comm_radius)).any(2) == 0) & (r[:, :, None] > 0) & (r.sum(1) > 1)[:, None, None]
        return obs | inter | alone.flatten(1).any(1)
