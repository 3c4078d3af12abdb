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
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..data.samples import SampleConfig
from .diffusion import NoiseSchedule
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

    def sdf_scale(self, step: int) -> float:
        """The ramp-in factor of lambda_4 at optimizer step `step`."""
        if step < self.sdf_ramp_start:
            return 0.0
        return 1.0 if self.sdf_ramp_steps <= 0 else min(1.0, (step - self.sdf_ramp_start) / self.sdf_ramp_steps)


def check(cfg: LossConfig) -> None:
    if cfg.traj_reduction not in ("mean", "sum"):
        raise ValueError(f"loss.traj_reduction must be 'mean' or 'sum', got {cfg.traj_reduction!r}")
    bad = [k for k in ("traj", "wp", "occ", "sdf", "sdf_threshold") if getattr(cfg, k) < 0]
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
                     sample_cfg: SampleConfig, generator: torch.Generator | None = None, step: int | None = None
                     ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss (scalar tensor) and per-term figures for logging. batch: a collated sample batch on device;
    `step` (the optimizer step) applies the ramp-in of lambda_4, None = the full weight."""
    x0 = batch["chunk"]  # (B, R, H, 2)
    B = x0.shape[0]
    real = batch["robot_mask"].float()  # (B, R)
    fixed = batch["traj_mask"].float() * real
    gen = real - fixed
    k = torch.randint(0, sched.K, (B,), device=x0.device, generator=generator)
    eps = torch.randn(x0.shape, device=x0.device, generator=generator)
    xk = torch.where(fixed.bool()[:, :, None, None], x0, sched.q_sample(x0, k, eps))
    aux = loss_cfg.wp > 0 or loss_cfg.occ > 0 or loss_cfg.sdf > 0
    out = model(xk, k, batch, aux=aux)

    terms: dict[str, torch.Tensor] = {}
    sq = (out["eps"] - eps) ** 2  # (B, R, H, 2)
    terms["traj"] = _masked_mean(sq.mean(dim=(2, 3)) if loss_cfg.traj_reduction == "mean" else sq.sum(dim=(2, 3)), gen)
    if loss_cfg.wp > 0:
        terms["wp"] = _masked_mean(((out["waypoints"] - batch["waypoints"]) ** 2).sum(-1).mean(-1), real)
    if loss_cfg.occ > 0:
        bce = sum(F.binary_cross_entropy_with_logits(out[key], batch[key], reduction="none").mean(dim=(2, 3))
                  for key in ("occ_small", "occ_large"))
        terms["occ"] = _masked_mean(bce, real)
    if loss_cfg.sdf > 0:
        th = loss_cfg.sdf_threshold
        x0_hat = torch.where(fixed.bool()[:, :, None, None], x0, sched.predict_x0(xk, k, out["eps"]))
        traj = decode_chunk(x0_hat, batch["start"], sample_cfg)  # (B, R, H, 2)
        wps = batch["start"][:, :, None, :] + out["waypoints"] * sample_cfg.waypoint_scale  # (B, R, K, 2)
        # Weighted by abar_k: x0_hat = (x_k - sqrt(1 - abar) eps_hat) / sqrt(abar) amplifies the noise
        # prediction by up to 1/sqrt(abar) ~ 300 at the noisiest steps, where the penalty would otherwise swamp
        # the denoising gradient (measured: L_traj stops falling); the weight bounds d(penalty)/d(eps_hat).
        w = sched.abar[k][:, None, None]
        norm = th if loss_cfg.sdf_normalize else 1.0
        pen_traj = w * (F.relu(th - sdf_at(batch["sdf"], traj)) / norm) ** 2  # (B, R, H)
        pen_wp = (F.relu(th - sdf_at(batch["sdf"], wps)) / norm) ** 2  # (B, R, K)
        H, K = pen_traj.shape[-1], pen_wp.shape[-1]
        total = (loss_cfg.sdf_traj * (pen_traj.sum(-1) * gen).sum() + loss_cfg.sdf_wp * (pen_wp.sum(-1) * real).sum())
        terms["sdf"] = total / (gen.sum() * H + real.sum() * K).clamp(min=1)
    sdf_w = loss_cfg.sdf * (1.0 if step is None else loss_cfg.sdf_scale(step))
    weights = {"traj": loss_cfg.traj, "wp": loss_cfg.wp, "occ": loss_cfg.occ, "sdf": sdf_w}
    loss = sum(weights[name] * v for name, v in terms.items())
    metrics = {f"losses/{name}": v.detach() for name, v in terms.items()}  # tensors: no device sync here
    metrics["losses/total"] = loss.detach()
    return loss, metrics
