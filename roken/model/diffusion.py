"""DDPM noise schedule and the samplers: stochastic DDPM (with every step's mean, sigma and log-probability, as
GRPO needs them) and few-step DDIM, both with conditional masks.

Steps are indexed k = 0..K-1 with x_k = sqrt(abar_k) x_0 + sqrt(1 - abar_k) eps; sampling walks k = K-1..0
and x_{-1} is the clean chunk. Robots with trajectory mask 1 are conditions: their chunk is held at the given
value in every model input and returned unchanged. The map is encoded once per plan (keys/values of every
cross-attention layer) and G candidates of one prompt share it inside one batch.

DDPM transitions use the posterior N(mu_k, sigma_k^2) with mu_k computed from the clipped x_0 prediction and
sigma_k^2 the posterior variance, where the last step (k = 0, variance 0) takes the k = 1 value (improved-DDPM's
"clipped" log-variance). So every transition, the last included, is a proper Gaussian with a finite
log-probability, and the noise it adds at the end is tiny (about 0.01 of a full-speed move).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .dit import MapContext, RokenDiT

PREDICTIONS = ("eps", "v", "x0")
COND_KEYS = ("start", "rel_goal", "goal_mask", "traj_mask", "robot_mask", "prev_move")


@dataclass
class DiffusionConfig:
    num_steps: int = 100  # K training / DDPM steps
    schedule: str = "cosine"  # "cosine" (Nichol & Dhariwal) or "linear" (Ho et al.)
    beta_start: float = 1e-4  # linear schedule only
    beta_end: float = 0.02
    clip_sample: float = 1.0  # clip the predicted clean chunk to [-c, c]; a full-speed move is 1 (0 = no clip)
    # What the denoiser outputs (and its loss compares): "eps", the noise (the paper's, DDPM's); "v" =
    # sqrt(abar) eps - sqrt(1 - abar) x0 (Salimans & Ho 2022: the eps loss weighted by 1 / abar, so the
    # noisiest steps, which choose the plan, are learned as much as the last ones); "x0", the clean chunk
    # (Diffuser's, Janner et al. 2022: the eps loss weighted by (1 - abar) / abar). The samplers, GRPO and the
    # auxiliary losses read it as eps through NoiseSchedule.eps_from, so all work with any of the three.
    prediction: str = "eps"


def check(cfg: DiffusionConfig) -> None:
    if cfg.schedule not in ("cosine", "linear"):
        raise ValueError(f"diffusion.schedule must be 'cosine' or 'linear', got {cfg.schedule!r}")
    if cfg.prediction not in PREDICTIONS:
        raise ValueError(f"diffusion.prediction must be one of {', '.join(PREDICTIONS)}, got {cfg.prediction!r}")


class NoiseSchedule:
    def __init__(self, cfg: DiffusionConfig, device: torch.device | str = "cpu"):
        check(cfg)
        K = cfg.num_steps
        if cfg.schedule == "cosine":
            s = 0.008
            f = torch.cos((torch.arange(K + 1, dtype=torch.float64) / K + s) / (1 + s) * math.pi / 2) ** 2
            betas = (1 - f[1:] / f[:-1]).clamp(max=0.999)
        else:  # linear
            betas = torch.linspace(cfg.beta_start, cfg.beta_end, K, dtype=torch.float64)
        self.cfg, self.K = cfg, K
        alphas = 1 - betas
        abar = torch.cumprod(alphas, 0)
        abar_prev = torch.cat([torch.ones(1, dtype=torch.float64), abar[:-1]])
        var = betas * (1 - abar_prev) / (1 - abar)
        var[0] = var[1] if K > 1 else betas[0]
        t = {
            "betas": betas, "abar": abar, "abar_prev": abar_prev, "sigma": var.sqrt(),
            "coef_x0": betas * abar_prev.sqrt() / (1 - abar),  # posterior mean = coef_x0 x0 + coef_xk x_k
            "coef_xk": (1 - abar_prev) * alphas.sqrt() / (1 - abar),
        }
        for name, v in t.items():
            setattr(self, name, v.float().to(device))

    def _at(self, name: str, k: torch.Tensor) -> torch.Tensor:
        return getattr(self, name)[k].view(-1, 1, 1, 1)  # broadcast over (R, H, 2)

    def q_sample(self, x0, k, eps):
        a = self._at("abar", k)
        return a.sqrt() * x0 + (1 - a).sqrt() * eps

    def eps_from(self, out, xk, k):
        """The noise estimate (B, R, H, 2) from the denoiser's output `out` at x_k (diffusion.prediction)."""
        p = self.cfg.prediction
        if p == "eps":
            return out
        a = self._at("abar", k)
        if p == "v":  # eps = sqrt(abar) v + sqrt(1 - abar) x_k
            return a.sqrt() * out + (1 - a).sqrt() * xk
        return (xk - a.sqrt() * out) / (1 - a).sqrt()  # x0

    def target(self, x0, eps, k):
        """What the denoiser should output for the clean chunk x0 noised by eps at step k (its loss target)."""
        p = self.cfg.prediction
        if p == "eps":
            return eps
        if p == "v":
            a = self._at("abar", k)
            return a.sqrt() * eps - (1 - a).sqrt() * x0
        return x0

    def predict_x0(self, xk, k, eps):
        a = self._at("abar", k)
        x0 = (xk - (1 - a).sqrt() * eps) / a.sqrt()
        c = self.cfg.clip_sample
        return x0.clamp(-c, c) if c > 0 else x0

    def posterior(self, xk, k, eps) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean (B, R, H, 2) and sigma (B, 1, 1, 1) of p(x_{k-1} | x_k)."""
        x0 = self.predict_x0(xk, k, eps)
        return self._at("coef_x0", k) * x0 + self._at("coef_xk", k) * xk, self._at("sigma", k)


def gaussian_logprob(x, mean, sigma, mask) -> torch.Tensor:
    """log N(x; mean, sigma^2 I) over the elements where mask (B, R) is true -> (B,), in float32 even when the
    model ran in bf16 (GRPO's ratios are differences of sums over hundreds of elements)."""
    x, mean, sigma = x.float(), mean.float(), sigma.float()
    lp = -0.5 * ((x - mean) / sigma) ** 2 - torch.log(sigma) - 0.5 * math.log(2 * math.pi)
    return (lp * mask[:, :, None, None]).sum(dim=(1, 2, 3))


@dataclass
class Prompt:
    """The conditioning of a batch of plans, expanded to B = Bm * G rows (G candidates per map)."""
    cond: dict  # COND_KEYS tensors with B rows
    given: torch.Tensor  # (B, R, H, 2) chunks of the conditioned robots (anything elsewhere)
    fixed: torch.Tensor  # (B, R, 1, 1) bool: traj_mask
    generated: torch.Tensor  # (B, R) float: real robots that are generated
    ctx: MapContext


def make_prompt(model: RokenDiT, cond: dict, given: torch.Tensor | None = None, num_candidates: int = 1,
                ctx: MapContext | None = None) -> Prompt:
    """cond holds COND_KEYS with Bm rows and `map` (Bm, 3, S, S); encodes the map once."""
    G = num_candidates
    rep = {key: cond[key].repeat_interleave(G, 0) for key in COND_KEYS if key in cond}  # prev_move is optional
    B, R = rep["start"].shape[:2]
    H = model.cfg.horizon
    given = torch.zeros(B, R, H, 2, device=rep["start"].device) if given is None else given.repeat_interleave(G, 0)
    fixed = rep["traj_mask"].bool()[:, :, None, None]
    generated = (rep["robot_mask"].bool() & ~rep["traj_mask"].bool()).float()
    return Prompt(rep, given, fixed, generated, ctx if ctx is not None else model.encode_map(cond["map"]))


def _randn(shape, generator, device, noise):
    """Standard normal noise: from `noise(shape)` when given (the planner draws it per episode, so an episode's
    samples do not depend on which other episodes share its batch), else from `generator`."""
    return noise(shape).to(device) if noise is not None else torch.randn(shape, generator=generator, device=device)


def model_eps(model, sched: NoiseSchedule, prompt: Prompt, x, ks: torch.Tensor) -> torch.Tensor:
    """The model's noise estimate (B, R, H, 2) at x_k, the conditioned robots held at their given chunks."""
    xin = torch.where(prompt.fixed, prompt.given, x)
    return sched.eps_from(model(xin, ks, prompt.cond, ctx=prompt.ctx)["eps"], xin, ks)


def _eps(model, sched: NoiseSchedule, prompt: Prompt, x, k: int):
    ks = torch.full((x.shape[0],), k, device=x.device, dtype=torch.long)
    return model_eps(model, sched, prompt, x, ks), ks


@dataclass
class Rollout:
    chunk: torch.Tensor  # (B, R, H, 2) sampled chunks (conditioned robots exactly as given)
    latents: torch.Tensor | None = None  # (K+1, B, R, H, 2): x_{K-1}, ..., x_0, x_{-1}
    means: torch.Tensor | None = None  # (K, B, R, H, 2)
    sigmas: torch.Tensor | None = None  # (K,)
    logprobs: torch.Tensor | None = None  # (K, B) over generated robots
    steps: torch.Tensor | None = None  # (K,) the k of each transition


@torch.no_grad()
def ddpm_sample(model: RokenDiT, sched: NoiseSchedule, prompt: Prompt, generator: torch.Generator | None = None,
                record: bool = False, noise=None) -> Rollout:
    x = _randn(prompt.given.shape, generator, prompt.given.device, noise)
    x = torch.where(prompt.fixed, prompt.given, x)
    lat, means, sigmas, lps = [x], [], [], []
    for k in range(sched.K - 1, -1, -1):
        eps, ks = _eps(model, sched, prompt, x, k)
        mean, sigma = sched.posterior(x, ks, eps)
        x_new = mean + sigma * _randn(x.shape, generator, x.device, noise)
        x_new = torch.where(prompt.fixed, prompt.given, x_new)
        if record:
            lat.append(x_new)
            means.append(mean)
            sigmas.append(sigma.view(-1)[0])
            lps.append(gaussian_logprob(x_new, mean, sigma, prompt.generated))
        x = x_new
    if not record:
        return Rollout(x)
    steps = torch.arange(sched.K - 1, -1, -1, device=x.device)
    return Rollout(x, torch.stack(lat), torch.stack(means), torch.stack(sigmas), torch.stack(lps), steps)


def transition_logprob(model: RokenDiT, sched: NoiseSchedule, prompt: Prompt, x_k: torch.Tensor, k: torch.Tensor,
                       x_prev: torch.Tensor) -> torch.Tensor:
    """log p_theta(x_prev | x_k) (B,) under the current weights, with gradients: GRPO's ratio."""
    eps = model_eps(model, sched, prompt, x_k, k)
    mean, sigma = sched.posterior(x_k, k, eps)
    return gaussian_logprob(x_prev, mean, sigma, prompt.generated)


def ddim_steps(K: int, steps: int) -> list[int]:
    return sorted({int(round(v)) for v in torch.linspace(K - 1, 0, max(steps, 1)).tolist()}, reverse=True)


@torch.no_grad()
def ddim_sample(model: RokenDiT, sched: NoiseSchedule, prompt: Prompt, steps: int = 10, eta: float = 0.0,
                generator: torch.Generator | None = None, noise=None, guide=None, guide_steps: int = 0,
                stop: int | None = None, start: int = 0, latent: torch.Tensor | None = None) -> Rollout:
    """DDIM (Song et al.) over `steps` evenly spaced diffusion steps; eta = 0 is deterministic. `guide(x0, given,
    fixed)` (roken.plan.guidance) moves the predicted clean chunk at the last `guide_steps` steps. `stop`: only
    the first `stop` steps, the latent there returned as `chunk` (the `selfcost` term grades the next step).
    `start`, `latent`: begin at the start-th step from that latent (SDEdit-style) instead of from pure noise."""
    x = _randn(prompt.given.shape, generator, prompt.given.device, noise) if latent is None else latent
    seq = ddim_steps(sched.K, steps)
    for i, k in list(enumerate(seq[:stop]))[start:]:
        eps, ks = _eps(model, sched, prompt, x, k)
        a = sched.abar[k]
        a_prev = sched.abar[seq[i + 1]] if i + 1 < len(seq) else torch.ones((), device=x.device)
        x0 = sched.predict_x0(x, ks, eps)
        if guide is not None and i >= len(seq) - guide_steps:
            x0 = guide(x0, prompt.given, prompt.fixed, last=i == len(seq) - 1)
        eps = (x - a.sqrt() * x0) / (1 - a).sqrt()  # consistent with the clipped x0
        sigma = eta * ((1 - a_prev) / (1 - a) * (1 - a / a_prev)).clamp(min=0).sqrt()
        x = a_prev.sqrt() * x0 + (1 - a_prev - sigma ** 2).clamp(min=0).sqrt() * eps
        if eta > 0:
            x = x + sigma * _randn(x.shape, generator, x.device, noise)
    return Rollout(torch.where(prompt.fixed, prompt.given, x))
