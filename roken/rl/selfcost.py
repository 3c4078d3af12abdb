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
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ..data.condition import build_condition
from ..data.samples import SampleConfig
from ..model.diffusion import COND_KEYS, NoiseSchedule, ddim_sample, ddim_steps, make_prompt
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
    seed: int = 0


def check(sc: SelfCostConfig, need_states: bool = True) -> None:
    """need_states=False: the caller supplies them (DAgger: each round's rollouts)."""
    if sc.weight < 0:
        raise ValueError(f"selfcost.weight={sc.weight}: must be >= 0 (0 = off)")
    if sc.weight > 0 and need_states and not sc.states.strip():
        raise ValueError("selfcost.weight > 0 needs selfcost.states: evaluation folders of closed-loop rollouts on "
                         "train maps (pipelines/evaluate.py --maps train --out DIR, or a DAgger round's rollouts/)")
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
        seq = ddim_steps(sched.K, sc.steps)
        # the graded step: one of the grad_steps before the last (the last, k = 0, scales the noise prediction by
        # sqrt(1 - abar_0) ~ 0.01: its clean chunk hardly depends on the weights, so its gradient is nil)
        graded = max(len(seq) - 2 - int(rng.integers(min(sc.grad_steps, len(seq) - 1))), 0)
        # DDIM (eta = 0) to the graded step without gradients, as the planner samples; then one model call with them
        x = ddim_sample(model, sched, prompt, sc.steps, noise=lambda shape: torch.randn(shape, generator=gen),
                        stop=graded).chunk  # (B G, R, H, 2)
        ks = torch.full((x.shape[0],), seq[graded], device=dev, dtype=torch.long)
        x0 = sched.predict_x0(x, ks, model(x, ks, prompt.cond, ctx=prompt.ctx)["eps"])
        start = prompt.cond["start"]
        p = decode_chunk(x0, start, self.samples)  # (B G, R, H, 2) metres
        real = np.stack([c["robot_mask"] for c in conds])
        leader = np.array([int(np.argmax(c["goal_mask"])) for c in conds])
        sdf, geo = map(np.stack, zip(*(self.fields(e) for e in eps)))
        guide = Guide(self.pc, self.tc, self.samples, np.stack([c["start"] for c in conds]), real, real, leader,
                      sdf, geo, G, dev)
        cost = guide.cost(p)  # (B G,)
        with torch.no_grad():  # how many of the sampled executed moves break a hard constraint
            viol = self.violating(p[:, :, :self.pc.replan_every], torch.as_tensor(guide.sdf, device=dev),
                                  torch.as_tensor(guide.real, device=dev))
        loss = sc.weight * cost.mean()
        return loss, {"losses/selfcost": cost.mean().detach(), "selfcost/violating": viol.float().mean()}

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
