"""GRPO rollout workers: a model copy, the dataset's episodes and the reward's privileged fields, kept across
iterations (one per Ray actor, or one in-process with --workers 0).

A unit is a few prompts and a `Shared` handle on the weights of one version. The worker loads the weights when
the version changes (one object-store fetch per actor per iteration), samples G candidates per prompt with the
DDPM chain (recording the trained transitions), scores them with the privileged reward, and returns one
`Group` per prompt stamped with the version it actually sampled with.
"""
from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import torch

from ..data.condition import decode_chunk
from ..data.samples import EpisodeBank
from ..plan.planner import RokenPlanner
from ..world.grid import GridMap
from ..world.tasks import TaskConfig
from .config import RLConfig
from .grpo import Group
from .policy import group_prompt, sample_recorded, trained_steps
from .prompts import condition, state
from .rewards import geodesic_to, privileged, score


def prompt_seed(seed: int, version: int, prompt: tuple[int, int]) -> int:
    """Noise seed of one prompt's group: the same run, iteration and prompt give the same candidates."""
    return int(np.random.SeedSequence([seed, version, prompt[0], prompt[1]]).generate_state(1)[0])


class RolloutWorker:
    def __init__(self, blob: dict, data: str, tc: TaskConfig, rc: RLConfig, device: str = "cpu"):
        self.planner = RokenPlanner.unpack(blob, device)
        self.model, self.sched, self.cfg = self.planner.model, self.planner.schedule, self.planner.cfg
        self.bank = EpisodeBank.from_folder(data, self.cfg.canvas)
        self.tc, self.rc, self.version = tc, rc, -1
        self.maps: dict[int, GridMap] = {}
        self.geodesic: dict[tuple, np.ndarray] = {}  # (map, goal) -> field; prompts of one episode share it

    def set_weights(self, shared) -> None:
        if shared.version != self.version:
            state = shared.get()
            self.model.load_state_dict({k: v.to(self.planner.device) for k, v in state.items()})
            self.version = shared.version

    def _gm(self, m: int) -> GridMap:
        if m not in self.maps:
            self.maps[m] = GridMap(self.bank.map_ids[m], self.bank.occupancy[m])
        return self.maps[m]

    @torch.no_grad()
    def group(self, prompt: tuple[int, int]) -> Group:
        rc, cfg, dev = self.rc, self.cfg, self.planner.device
        G = rc.group_size
        cond = condition(self.bank, prompt, cfg)
        p = group_prompt(self.model, cond, G, dev)
        gen = torch.Generator().manual_seed(prompt_seed(rc.seed, self.version, prompt))
        steps = trained_steps(self.sched.K, rc.train_transitions, rc.transitions, rc.skip_final, gen)
        rec = sample_recorded(self.model, self.sched, p, steps, gen)
        pos, leader, goal, m = state(self.bank, prompt)
        plan = decode_chunk(rec.chunk.float().cpu().numpy(), pos[None].astype(np.float32), cfg)  # (G, n, H, 2)
        key = (m, float(goal[0]), float(goal[1]))
        if key not in self.geodesic:
            if len(self.geodesic) > 256:
                self.geodesic.clear()
            self.geodesic[key] = geodesic_to(self._gm(m), goal)
        info = privileged(self._gm(m), pos, leader, goal, cfg.horizon * cfg.step_scale, self.geodesic[key])
        rewards, terms = score(plan, pos, info, self.tc, rc, cfg.interval)
        return Group(prompt=(int(prompt[0]), int(prompt[1])), version=self.version, steps=rec.steps,
                     x_k=rec.x_k.float().cpu().numpy(), x_prev=rec.x_prev.float().cpu().numpy(),
                     logp=rec.logp.cpu().numpy(), rewards=rewards,
                     terms={k: np.asarray(terms[k]) for k in ("hard", "obs", "inter", "conn", "reach")})


def rollout_unit(ctx: dict, payload: dict, cache: dict) -> list[Group]:
    """Unit function (roken.units): ctx {checkpoint blob, data, task, rl, device}; payload {prompts, weights}."""
    if "worker" not in cache:
        from ..configtools import from_dict

        cache["worker"] = RolloutWorker(ctx["checkpoint"], ctx["data"], from_dict(TaskConfig, ctx["task"]),
                                        from_dict(RLConfig, ctx["rl"]), ctx.get("device", "cpu"))
    _injected_failure()
    w = cache["worker"]
    w.set_weights(payload["weights"])
    return [w.group(tuple(p)) for p in payload["prompts"]]


def _injected_failure() -> None:
    """Fault injection for the recovery test: ROKEN_KILL_ROLLOUT=MARKER makes the first worker that reads it
    SIGKILL itself once (the marker file records it), as an OOM kill or a lost node would."""
    marker = os.environ.get("ROKEN_KILL_ROLLOUT")
    if marker and not os.path.exists(marker):
        Path(marker).write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
