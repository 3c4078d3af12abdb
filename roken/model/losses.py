"""The paper's pretraining loss L = l1 L_traj + l2 L_wp + l3 L_occ + l4 L_sdf (appendix "Loss Functions").

  L_traj  MSE between the added and the predicted noise, over generated robots (conditions are not noised)
  L_wp    MSE of the K = 5 waypoints (normalised, relative to start), over real robots
  L_occ   binary cross-entropy of the 7 x 7 local occupancy at 1x plus at 3x, from the middle layer
  L_sdf   [ReLU(d_thres - sdf(p))]^2 on the trajectory integrated from the predicted clean chunk (generated
          robots, H points each) and on the predicted waypoints (real robots, K points each), averaged over
          those N (H + K) points as in the appendix; sdf is the map's signed distance in metres, read with
          differentiable bilinear interpolation (grid_sample), d_thres = 4 px. Beyond the paper, the trajectory
          part is weighted by abar_k, the signal fraction of the noisy input (see the comment below).

A weight of 0 switches a term off (and skips its computation): the ablation table's rows are weight settings.

`loss.sdf_mode` says where the trajectory part of L_sdf acts. The closed loop executes only a chunk's first
`replan_every` moves, and the paper's form integrates the predicted moves by cumulative sum, so move h
receives the summed gradient of points h..H-1: measured on the shipped model, the SDF gradient on the
predicted noise is 2.2x the denoising gradient at move 0 and 0.25x at move 15, and the executed follower
moves came out unrelated to the expert's (cosine +0.03). The modes (README "Which SDF term"):
  paper     points integrated from the predicted chunk, weighted by abar_k (the shipped model's loss)
  off       no trajectory SDF term (the waypoint part stays, with loss.sdf_wp)
  stopgrad  point h = start + stop_grad(moves 0..h-1) + move h: each point's penalty moves only its own move
  low_noise the paper's points, only for draws with k < loss.sdf_max_k (x0_hat is then a sharp estimate)

`train.noise_draws` = K (Mini-Diffuser): each sample's map is encoded once and the decoder sees K independent
(k, eps) draws of the same clean chunk against that one map context (rows ordered sample-major, the layout the
model already uses for G candidates of one prompt). L_traj and L_sdf average over the K draws; the auxiliary
losses (waypoints, occupancy) are taken once per sample, on its first draw.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..data.samples import SampleConfig
from .diffusion import COND_KEYS, NoiseSchedule
from .dit import RokenDiT


@dataclass
class LossConfig:
    traj: float = 1.0  # lambda_1
    wp: float = 1.0  # lambda_2
    occ: float = 0.1  # lambda_3
    sdf: float = 1.0  # lambda_4
    sdf_threshold: float = 4.0  # d_thres, metres (= pixels)
    sdf_traj: float = 1.0  # lambda_sdf^traj
    sdf_wp: float = 1.0  # lambda_sdf^wp
    # How the terms are balanced (README "Loss balance"). The paper's formulation is traj_reduction=mean,
    # sdf_normalize=false, sdf=1. Its L_sdf is in m^2 while L_traj and L_wp are in normalised units, and the
    # expert's own chunks score 1.8 per point, so at weight 1 it drowns the denoising loss (measured: L_traj
    # 1.00 -> 0.95 in 400 steps vs 0.12 without it). The default divides the penalty by d_thres^2 (a per-point
    # value in [0, 1], dimensionless like the other terms) and ramps lambda_4 in once denoising has started.
    traj_reduction: str = "mean"  # "mean" over the chunk's elements (paper) or "sum" over them
    sdf_normalize: bool = True  # penalty [ReLU(d_thres - sdf) / d_thres]^2 instead of metres^2
    sdf_ramp_start: int = 0  # optimizer step at which lambda_4 starts to ramp in from 0
    sdf_ramp_steps: int = 0  # steps to reach the full lambda_4 (0 = at once)
    sdf_mode: str = "paper"  # paper | off | stopgrad | low_noise (module docstring)
    sdf_max_k: int = 10  # low_noise: the trajectory penalty applies to draws with k < sdf_max_k
    # L_traj weight of the first `executed_moves` chunk moves (the ones the closed loop executes) relative to the
    # others; the weights are normalised to mean 1 over the chunk, so 1.0 is the paper's uniform mean
    executed_weight: float = 1.0
    executed_moves: int = 2
    # Beyond the paper: a separation term on the predicted clean chunk, [ReLU(sep_distance - d_ij) / sep_distance]^2
    # over robot pairs (at least one generated) at every chunk point, weighted by abar_k like L_sdf and built from
    # the same points (loss.sdf_mode stopgrad: each point moves only its own move). Plain Roken's episodes
    # come to robot-robot contact (177 of 200 `val` episodes, median first contact at step 23), which the
    # paper's losses never penalise; the expert keeps pairs >= 3.1 m (10th percentile of episode minima), so a
    # hinge at 2.5 m (d_coll_min + 0.5) seldom acts on demonstrations. Measured: it does not lower the contacts
    # (README "Two levers screened"), off by default.
    sep: float = 0.0  # weight; 0 = off (the paper's loss)
    sep_distance: float = 2.5  # metres

    def __post_init__(self):
        if self.sdf_mode in (False, "False", "false", "no"):  # YAML reads a bare `off` as false
            self.sdf_mode = "off"

    def sdf_scale(self, step: int) -> float:
        """The ramp-in factor of lambda_4 at optimizer step `step`."""
        if step < self.sdf_ramp_start:
            return 0.0
        return 1.0 if self.sdf_ramp_steps <= 0 else min(1.0, (step - self.sdf_ramp_start) / self.sdf_ramp_steps)


SDF_MODES = ("paper", "off", "stopgrad", "low_noise")


def check(cfg: LossConfig) -> None:
    if cfg.sdf_mode not in SDF_MODES:
        raise ValueError(f"loss.sdf_mode must be one of {', '.join(SDF_MODES)}, got {cfg.sdf_mode!r}")
    if cfg.traj_reduction not in ("mean", "sum"):
        raise ValueError(f"loss.traj_reduction must be 'mean' or 'sum', got {cfg.traj_reduction!r}")
    bad = [k for k in ("traj", "wp", "occ", "sdf", "sdf_threshold", "executed_weight", "executed_moves", "sep",
                       "sep_distance")
           if getattr(cfg, k) < 0]
    if bad:
        raise ValueError(f"loss.{bad[0]} must be >= 0, got {getattr(cfg, bad[0])}")


def decode_chunk(chunk: torch.Tensor, start: torch.Tensor, cfg: SampleConfig) -> torch.Tensor:
    """(B, R, H, 2) chunk, (B, R, 2) start -> (B, R, H, 2) positions in metres (torch twin of samples.decode_chunk)."""
    if cfg.representation == "relative":
        return start[:, :, None, :] + torch.cumsum(chunk, dim=2) * cfg.step_scale
    return (chunk + 1.0) * cfg.pos_scale


def sdf_at(sdf: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """Bilinear signed distance of the cell-centred field sdf (B, S, S) at pts (B, ..., 2) metres -> (B, ...).

    With align_corners=False, grid coordinate -1 is the left edge of cell 0 and +1 the right edge of the last
    cell, so the point x in metres is 2 x / S - 1 and cell centres land on samples; outside, the border value."""
    B, S = sdf.shape[0], sdf.shape[-1]
    grid = (pts.reshape(B, -1, 1, 2) * (2.0 / S) - 1.0).to(sdf.dtype)
    out = F.grid_sample(sdf[:, None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out.view(pts.shape[:-1])


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of x (B, R) over mask (B, R); 0 when the mask is empty."""
    return (x * mask).sum() / mask.sum().clamp(min=1)


def pretraining_loss(model: RokenDiT, sched: NoiseSchedule, batch: dict, loss_cfg: LossConfig,
                     sample_cfg: SampleConfig, generator: torch.Generator | None = None, step: int | None = None,
                     draws: int = 1, k: torch.Tensor | None = None, eps: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss (scalar tensor) and per-term figures for logging. batch: a collated sample batch on device
    (B samples); `draws` = K noise draws per sample (B K decoder rows, one map encoding per sample); `k` (B K,)
    and `eps` (B K, R, H, 2) give the draws explicitly (tests), else they come from `generator`. `step` (the
    optimizer step) applies the ramp-in of lambda_4, None = the full weight."""
    B = batch["chunk"].shape[0]
    K = max(int(draws), 1)
    rep = (lambda v: v.repeat_interleave(K, 0)) if K > 1 else (lambda v: v)
    x0 = rep(batch["chunk"])  # (BK, R, H, 2): sample-major, draw-minor
    real = rep(batch["robot_mask"].float())  # (BK, R)
    fixed = rep(batch["traj_mask"].float()) * real
    gen = real - fixed
    if k is None:
        k = torch.randint(0, sched.K, (B * K,), device=x0.device, generator=generator)
    if eps is None:
        eps = torch.randn(x0.shape, device=x0.device, generator=generator)
    xk = torch.where(fixed.bool()[:, :, None, None], x0, sched.q_sample(x0, k, eps))
    aux = loss_cfg.wp > 0 or loss_cfg.occ > 0 or loss_cfg.sdf > 0
    # the map stays at B rows: the model encodes it once and shares the context across each sample's K rows
    cond = {key: rep(batch[key]) for key in COND_KEYS} | {"map": batch["map"]}
    out = model(xk, k, cond, aux=aux)
    first = slice(None, None, K)  # each sample's first draw: the auxiliary losses, once per sample

    terms: dict[str, torch.Tensor] = {}
    # the denoiser's output against its target in its own parametrisation (diffusion.prediction)
    sq = (out["eps"] - sched.target(x0, eps, k)) ** 2  # (BK, R, H, 2)
    if loss_cfg.executed_weight != 1.0:
        H = sq.shape[2]
        w = torch.ones(H, device=sq.device)
        w[:loss_cfg.executed_moves] = loss_cfg.executed_weight
        sq = sq * (w * H / w.sum())[None, None, :, None]
    terms["traj"] = _masked_mean(sq.mean(dim=(2, 3)) if loss_cfg.traj_reduction == "mean" else sq.sum(dim=(2, 3)), gen)
    real1 = batch["robot_mask"].float()
    if loss_cfg.wp > 0:
        terms["wp"] = _masked_mean(((out["waypoints"][first] - batch["waypoints"]) ** 2).sum(-1).mean(-1), real1)
    if loss_cfg.occ > 0:
        bce = sum(F.binary_cross_entropy_with_logits(out[key][first], batch[key], reduction="none").mean(dim=(2, 3))
                  for key in ("occ_small", "occ_large"))
        terms["occ"] = _masked_mean(bce, real1)
    # the predicted clean chunk's points, built once for the trajectory SDF part and the separation term
    sdf_traj = loss_cfg.sdf > 0 and loss_cfg.sdf_mode != "off" and loss_cfg.sdf_traj != 0
    points = _predicted_points(sched, loss_cfg, sample_cfg, out, x0, xk, k, fixed, rep(batch["start"])) \
        if sdf_traj or loss_cfg.sep > 0 else None
    if loss_cfg.sdf > 0:
        terms["sdf"] = _sdf_term(sched, batch, loss_cfg, sample_cfg, out, x0, xk, k, fixed, gen, K, points)
    if loss_cfg.sep > 0:
        terms["sep"] = _sep_term(sched, batch, loss_cfg, sample_cfg, out, x0, xk, k, fixed, gen, real, K, points)
    sdf_w = loss_cfg.sdf * (1.0 if step is None else loss_cfg.sdf_scale(step))
    weights = {"traj": loss_cfg.traj, "wp": loss_cfg.wp, "occ": loss_cfg.occ, "sdf": sdf_w, "sep": loss_cfg.sep}
    loss = sum(weights[name] * v for name, v in terms.items())
    metrics = {f"losses/{name}": v.detach() for name, v in terms.items()}  # tensors: no device sync here
    metrics["losses/total"] = loss.detach()
    return loss, metrics


def _sdf_term(sched, batch, loss_cfg, sample_cfg, out, x0, xk, k, fixed, gen, K, points=None) -> torch.Tensor:
    """L_sdf: the trajectory part per loss.sdf_mode over the B K draws (averaged over draws), plus the waypoint
    part once per sample."""
    th = loss_cfg.sdf_threshold
    norm = th if loss_cfg.sdf_normalize else 1.0
    start = batch["start"].repeat_interleave(K, 0) if K > 1 else batch["start"]
    real1 = batch["robot_mask"].float()
    wps = batch["start"][:, :, None, :] + out["waypoints"][::K] * sample_cfg.waypoint_scale  # (B, R, Kw, 2)
    pen_wp = (F.relu(th - sdf_at(batch["sdf"], wps)) / norm) ** 2  # (B, R, Kw)
    H, Kw = x0.shape[2], pen_wp.shape[-1]
    wp_sum = loss_cfg.sdf_wp * (pen_wp.sum(-1) * real1).sum()
    if loss_cfg.sdf_mode == "off" or loss_cfg.sdf_traj == 0:
        return wp_sum / (real1.sum() * Kw).clamp(min=1)
    traj, w = points if points is not None else \
        _predicted_points(sched, loss_cfg, sample_cfg, out, x0, xk, k, fixed, start)
    # each sample's K draws read its one SDF (rows are sample-major): no K copies of the (S, S) field
    d = sdf_at(batch["sdf"], traj.view(batch["sdf"].shape[0], -1, 2)).view(traj.shape[:-1])  # (BK, R, H)
    pen_traj = w * (F.relu(th - d) / norm) ** 2  # (BK, R, H)
    traj_sum = loss_cfg.sdf_traj * (pen_traj.sum(-1) * gen).sum() / K  # mean over the draws
    return (traj_sum + wp_sum) / (gen.sum() / K * H + real1.sum() * Kw).clamp(min=1)


def _predicted_points(sched, loss_cfg, sample_cfg, out, x0, xk, k, fixed, start):
    """The predicted clean chunk as points in metres (BK, R, H, 2), per loss.sdf_mode, and its weight (BK, 1, 1)."""
    eps_hat = sched.eps_from(out["eps"], xk, k)  # the noise estimate, whatever the denoiser predicts
    x0_hat = torch.where(fixed.bool()[:, :, None, None], x0, sched.predict_x0(xk, k, eps_hat))
    if loss_cfg.sdf_mode == "stopgrad" and sample_cfg.representation == "relative":
        # point h = start + (moves 0..h-1, no gradient) + move h: a point's penalty moves only its own move
        before = torch.cumsum(x0_hat.detach(), dim=2) - x0_hat.detach()
        traj = start[:, :, None, :] + (before + x0_hat) * sample_cfg.step_scale
    else:
        traj = decode_chunk(x0_hat, start, sample_cfg)  # (BK, R, H, 2)
    # Weighted by abar_k: x0_hat = (x_k - sqrt(1 - abar) eps_hat) / sqrt(abar) amplifies the noise
    # prediction by up to 1/sqrt(abar) ~ 300 at the noisiest steps, where the penalty would otherwise swamp
    # the denoising gradient (measured: L_traj stops falling); the weight bounds d(penalty)/d(eps_hat).
    w = sched.abar[k][:, None, None]
    if loss_cfg.sdf_mode == "low_noise":
        w = w * (k < loss_cfg.sdf_max_k).float()[:, None, None]
    return traj, w


def _sep_term(sched, batch, loss_cfg, sample_cfg, out, x0, xk, k, fixed, gen, real, K, points=None
              ) -> torch.Tensor:
    """Separation of the predicted points: mean over (pair, point) of the weighted hinge, pairs of real robots
    with at least one generated (a given pair is fixed data, no gradient to give)."""
    if points is None:
        start = batch["start"].repeat_interleave(K, 0) if K > 1 else batch["start"]
        points = _predicted_points(sched, loss_cfg, sample_cfg, out, x0, xk, k, fixed, start)
    traj, w = points
    R = traj.shape[1]
    d = (traj[:, :, None] - traj[:, None]).pow(2).sum(-1).add(1e-9).sqrt()  # (BK, R, R, H)
    iu = torch.triu_indices(R, R, offset=1, device=traj.device)
    d = d[:, iu[0], iu[1]]  # (BK, P, H)
    pair = real[:, iu[0]] * real[:, iu[1]] * ((gen[:, iu[0]] + gen[:, iu[1]]) > 0).float()  # (BK, P)
    th = loss_cfg.sep_distance
    pen = w * (F.relu(th - d) / th) ** 2  # (BK, P, H)
    return (pen.sum(-1) * pair).sum() / (pair.sum() * d.shape[-1]).clamp(min=1)
