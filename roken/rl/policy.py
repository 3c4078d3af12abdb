"""The denoising chain as a policy (paper appendix): each DDPM transition x_k -> x_{k-1} is a Gaussian
N(mu_theta(x_k, c, k), sigma_k^2 I) with the schedule's sigma. What GRPO needs from it, and the numerics chosen:

- Log-probabilities are means over the generated robots' elements (padding and given robots masked out), not
  sums: a sum over 4 x 16 x 2 = 128 elements turns a small change of the mean into ratios of e^100 (DDPO's
  overflow). ratio = exp(mean_lp - mean_lp_old) is the per-element geometric-mean ratio.
- Only `train_transitions` transitions per candidate enter the loss: a random subset of the chain by default
  (the early, high-noise steps decide a chunk's shape; training only the last few, as DPPO does, changed
  nothing in a laptop run), or the last ones (`transitions="last"`). k = 0 is left out (`skip_final`): its
  sigma is the floored posterior sigma (about 0.01 of a full-speed move), where a mean shift of 0.01 already
  moves the log-ratio by ~1 (Flow-GRPO and DanceGRPO leave that step out too). The others run unrecorded.
- The sampler clips its x0 prediction to [-1, 1] (a full-speed move is 1). A plain clamp has zero gradient on
  the clipped elements, so the policy's mean uses a straight-through clip: the forward value is exactly the
  sampler's (ratios are exactly 1 right after a weight sync), the gradient passes as if unclipped.
- Only (x_k, x_{k-1}, k, log pi_old) of the trained transitions are kept; means are recomputed in the loss
  (storing them for 500 x 32 candidates and 100 steps would be about 2 GB per buffer).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

import numpy as np

from ..model.diffusion import COND_KEYS, NoiseSchedule, Prompt, make_prompt, model_eps
from ..model.dit import RokenDiT


def group_prompt(model: RokenDiT, cond: dict, G: int, device) -> Prompt:
    """One condition (build_condition's arrays) as a G-candidate prompt: the rollout worker and the learner build
    their batches the same way, so the learner's first ratio is exactly 1."""
    t = {k: torch.from_numpy(np.asarray(cond[k]))[None].to(device) for k in COND_KEYS + ("map", "chunk")}
    return make_prompt(model, {k: t[k] for k in COND_KEYS + ("map",)}, t["chunk"], G)


def trained_steps(K: int, count: int, how: str = "last", skip_final: bool = True,
                  generator: torch.Generator | None = None) -> list[int]:
    """The diffusion steps k whose transitions x_k -> x_{k-1} enter the loss, in sampling order (k descending)."""
    pool = list(range(1 if skip_final and K > 1 else 0, K))
    count = min(count, len(pool))
    if how == "last":
        chosen = pool[:count]
    else:
        chosen = [pool[i] for i in torch.randperm(len(pool), generator=generator)[:count].tolist()]
    return sorted(chosen, reverse=True)


def policy_mean(model: RokenDiT, sched: NoiseSchedule, prompt: Prompt, x: torch.Tensor,
                ks: torch.Tensor) -> torch.Tensor:
    """mu_theta(x_k, c, k) (B, R, H, 2): the DDPM posterior mean from the straight-through-clipped x0."""
    eps = model_eps(model, sched, prompt, x, ks)
    a = sched._at("abar", ks)
    x0 = (x - (1 - a).sqrt() * eps) / a.sqrt()
    c = sched.cfg.clip_sample
    if c > 0:
        x0 = x0 + (x0.clamp(-c, c) - x0).detach()
    return sched._at("coef_x0", ks) * x0 + sched._at("coef_xk", ks) * x


def mean_logprob(x: torch.Tensor, mean: torch.Tensor, sigma: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over the masked robots' elements of log N(x; mean, sigma^2) -> (B,), computed in float32."""
    x, mean, sigma = x.float(), mean.float(), sigma.float()
    lp = -0.5 * ((x - mean) / sigma) ** 2 - torch.log(sigma) - 0.5 * math.log(2 * math.pi)
    m = mask[:, :, None, None].float()
    count = (m.sum(dim=(1, 2, 3)) * x.shape[2] * x.shape[3]).clamp(min=1)
    return (lp * m).sum(dim=(1, 2, 3)) / count


def mean_kl(mean: torch.Tensor, mean_ref: torch.Tensor, sigma: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """KL(N(mean, s^2) || N(mean_ref, s^2)) = ||mean - mean_ref||^2 / (2 s^2), per element, masked mean -> (B,)."""
    kl = (mean.float() - mean_ref.float()) ** 2 / (2 * sigma.float() ** 2)
    m = mask[:, :, None, None].float()
    count = (m.sum(dim=(1, 2, 3)) * mean.shape[2] * mean.shape[3]).clamp(min=1)
    return (kl * m).sum(dim=(1, 2, 3)) / count


@dataclass
class Recorded:
    chunk: torch.Tensor  # (B, R, H, 2) the sampled clean chunks (given robots exactly as given)
    steps: list[int]  # the trained k, descending
    x_k: torch.Tensor  # (Kt, B, R, H, 2)
    x_prev: torch.Tensor  # (Kt, B, R, H, 2)
    logp: torch.Tensor  # (Kt, B) log pi_old, mean over generated elements


@torch.no_grad()
def sample_recorded(model: RokenDiT, sched: NoiseSchedule, prompt: Prompt, steps: list[int],
                    generator: torch.Generator | None = None) -> Recorded:
    """Full DDPM chain (every k); the transitions at `steps` are recorded with their log-probabilities."""
    shape, dev = prompt.given.shape, prompt.given.device
    randn = lambda: torch.randn(shape, generator=generator).to(dev)  # noqa: E731  (the generator lives on the CPU)
    x = randn()
    x = torch.where(prompt.fixed, prompt.given, x)
    want = set(steps)
    xs, xps, lps = [], [], []
    for k in range(sched.K - 1, -1, -1):
        ks = torch.full((shape[0],), k, device=x.device, dtype=torch.long)
        mean = policy_mean(model, sched, prompt, x, ks)
        sigma = sched._at("sigma", ks)
        x_new = torch.where(prompt.fixed, prompt.given, mean + sigma * randn())
        if k in want:
            xs.append(x)
            xps.append(x_new)
            lps.append(mean_logprob(x_new, mean, sigma, prompt.generated))
        x = x_new
    stack = (lambda v: torch.stack(v)) if xs else (lambda v: torch.zeros((0,) + tuple(shape)))
    return Recorded(x, sorted(want, reverse=True), stack(xs), stack(xps),
                    torch.stack(lps) if lps else torch.zeros(0, shape[0]))
