"""Validation on held-out episodes: the loss terms, and what sampled chunks do on the map and in the team.

A fixed set of prompts (full teams, the task's own goal, no given robots) is cut once from the validation
episodes. At each evaluation the EMA model samples one chunk per prompt with DDIM, decoded to metres, and we
measure, beside the same figures for the trivial "everyone stands still" chunk and for the expert's chunk:

  obs_frac      fraction of chunk points closer than d_obs_min to an obstacle (the metric's exact clearance)
  inter_frac    fraction of robot pairs, over the chunk's time points, closer than d_coll_min
  disconn_frac  fraction of chunks whose team is disconnected (range R) at some time point
  progress_m    the leader's progress toward the goal over the chunk, metres (straight-line distance)
  l2_m          mean distance to the expert's chunk point at the same time, metres

Move-wise, on the executed moves (the closed loop executes a plan's first `replan_every` moves only):

  val/first_move_cos_leader    cosine of the model's move 0 with the expert's, leaders (expert moves >= 5 cm)
  val/first_move_cos_follower  the same over followers
  val/l2_executed_m            mean distance to the expert over the first `executed` points, metres

A model that learned only the goal shows progress with many obstacle points; one that learned the map and the
team shows progress with violations close to standing still (and to the expert's).
"""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import replace

import numpy as np
import torch

from ..data.loader import collate, to_device
from ..data.samples import EpisodeBank, SampleConfig, decode_chunk, make_sample
from ..model.diffusion import COND_KEYS, NoiseSchedule, ddim_sample, make_prompt
from ..model.losses import LossConfig, pretraining_loss
from ..world.geometry import clearance, pad_for_clearance
from ..world.graph import connected

CHUNK_METRICS = ("obs_frac", "inter_frac", "disconn_frac", "progress_m", "l2_m")


def chunk_metrics(paths: np.ndarray, expert: np.ndarray, batch: dict, d_obs: float, d_coll: float,
                  radius: float) -> dict[str, float]:
    """paths, expert (V, R, H, 2) metres; batch the prompts' numpy arrays. Means over prompts."""
    obs, inter, disc, prog, l2 = [], [], [], [], []
    for v in range(len(paths)):
        n = int(batch["num_robots"][v])
        p = paths[v, :n]  # (n, H, 2)
        padded = pad_for_clearance((batch["map"][v, 0] > 0.5).astype(np.uint8))
        obs.append((clearance(padded, p.reshape(-1, 2)) < d_obs).mean())
        d = np.linalg.norm(p.transpose(1, 0, 2)[:, :, None] - p.transpose(1, 0, 2)[:, None], axis=-1)  # (H, n, n)
        iu = np.triu_indices(n, 1)
        inter.append((d[:, iu[0], iu[1]] < d_coll).mean() if n > 1 else 0.0)
        disc.append(float(not connected(d, radius).all()))
        lead = int(np.flatnonzero(batch["goal_mask"][v])[0])
        goal, start = batch["goal"][v], batch["start"][v, lead]
        prog.append(np.linalg.norm(start - goal) - np.linalg.norm(p[lead, -1] - goal))
        l2.append(np.linalg.norm(p - expert[v, :n], axis=-1).mean())
    return dict(zip(CHUNK_METRICS, (float(np.mean(x)) for x in (obs, inter, disc, prog, l2))))


class Validator:
    """Fixed validation prompts of a bank, scored with `evaluate(model)`."""

    def __init__(self, bank: EpisodeBank, samples: SampleConfig, loss: LossConfig, schedule: NoiseSchedule,
                 num_prompts: int = 64, ddim_steps: int = 10, d_obs: float = 1.0, d_coll: float = 2.0,
                 radius: float = 15.0, seed: int = 1234, batch_size: int = 64, executed: int = 2):
        cfg = replace(samples, condition_prob=0.0, subteam_prob=0.0, final_goal_prob=1.0, team_size_weights={})
        rng = np.random.default_rng(seed)
        picks = rng.choice(len(bank), size=num_prompts, replace=num_prompts > len(bank))
        self.samples = [make_sample(bank, int(i), np.random.default_rng([seed, k]), cfg) for k, i in enumerate(picks)]
        self.cfg, self.loss_cfg, self.schedule = cfg, loss, schedule
        self.ddim_steps, self.seed, self.batch_size, self.executed = ddim_steps, seed, batch_size, executed
        self.limits = (d_obs, d_coll, radius)
        self._reference: dict[str, float] | None = None

    def _batches(self):
        for a in range(0, len(self.samples), self.batch_size):
            yield collate(self.samples[a:a + self.batch_size])

    def reference(self) -> dict[str, float]:
        """The stand-still and expert rows (they do not depend on the model: computed once)."""
        if self._reference is None:
            out = {}
            for name in ("still", "expert"):
                paths, experts, batches = [], [], []
                for b in self._batches():
                    nb = {k: v.numpy() for k, v in b.items()}
                    expert = decode_chunk(nb["chunk"], nb["start"], self.cfg)
                    chunk = np.zeros_like(nb["chunk"]) if name == "still" else nb["chunk"]
                    if self.cfg.representation == "absolute" and name == "still":
                        chunk = np.repeat(nb["start"][:, :, None] / self.cfg.pos_scale - 1.0, self.cfg.horizon, 2)
                    paths.append(decode_chunk(chunk, nb["start"], self.cfg))
                    experts.append(expert)
                    batches.append(nb)
                m = chunk_metrics(np.concatenate(paths), np.concatenate(experts), _cat(batches), *self.limits)
                out |= {f"val/{name}/{k}": v for k, v in m.items()}
            self._reference = out
        return dict(self._reference)

    @torch.no_grad()
    def evaluate(self, model: torch.nn.Module, device: torch.device | str = "cpu",
                 autocast: torch.autocast | None = None) -> dict[str, float]:
        was_training = model.training
        model.eval()
        gen = torch.Generator(device=device).manual_seed(self.seed)
        sums: dict[str, float] = {}
        count = 0
        paths, experts, batches = [], [], []
        for b in self._batches():
            batch = to_device(b, device)
            n = len(b["chunk"])
            with autocast or nullcontext():
                _, logs = pretraining_loss(model, self.schedule, batch, self.loss_cfg, self.cfg, generator=gen)
                cond = {k: batch[k] for k in COND_KEYS + ("map",)}
                chunk = ddim_sample(model, self.schedule, make_prompt(model, cond), steps=self.ddim_steps,
                                    generator=gen).chunk
            for k, v in logs.items():
                sums[k] = sums.get(k, 0.0) + float(v) * n
            count += n
            nb = {k: v.numpy() for k, v in b.items()}
            paths.append(decode_chunk(chunk.float().cpu().numpy(), nb["start"], self.cfg))
            experts.append(decode_chunk(nb["chunk"], nb["start"], self.cfg))
            batches.append(nb)
        model.train(was_training)
        out = {f"val/{k}": v / count for k, v in sums.items()}
        paths, experts, nb = np.concatenate(paths), np.concatenate(experts), _cat(batches)
        m = chunk_metrics(paths, experts, nb, *self.limits)
        return out | {f"val/model/{k}": v for k, v in m.items()} | executed_moves(paths, experts, nb, self.executed) \
            | self.reference()


def executed_moves(paths: np.ndarray, expert: np.ndarray, batch: dict, executed: int = 2,
                   min_move: float = 0.05) -> dict[str, float]:
    """First-move cosine (leaders, followers) and L2 over the executed points; paths, expert (V, R, H, 2) m."""
    start = batch["start"]  # (V, R, 2)
    real = batch["robot_mask"] > 0
    lead = batch["goal_mask"] > 0
    a, b = paths[:, :, 0] - start, expert[:, :, 0] - start  # move 0, (V, R, 2)
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    cos = (a * b).sum(-1) / np.maximum(na * nb, 1e-9)
    cos = np.where(na < 1e-6, 0.0, cos)  # a model that stands still where the expert moves scores 0
    moving = real & (nb >= min_move)
    l2 = np.linalg.norm(paths[:, :, :executed] - expert[:, :, :executed], axis=-1).mean(-1)  # (V, R)

    def mean(x, m):
        return float(x[m].mean()) if m.any() else float("nan")
    return {"val/first_move_cos_leader": mean(cos, moving & lead), "val/first_move_cos_follower": mean(cos, moving & ~lead),
            "val/l2_executed_m": mean(l2, real)}


def _cat(batches: list[dict]) -> dict:
    return {k: np.concatenate([b[k] for b in batches]) for k in batches[0]}


def format_validation(m: dict[str, float]) -> str:
    """Model, stand-still and expert side by side."""
    head = f"{'chunk':<8}" + "".join(f"{k:>14}" for k in CHUNK_METRICS)
    lines = [head]
    for name in ("model", "still", "expert"):
        if f"val/{name}/obs_frac" in m:
            lines.append(f"{name:<8}" + "".join(f"{m[f'val/{name}/{k}']:>14.3f}" for k in CHUNK_METRICS))
    return "\n".join(lines)
