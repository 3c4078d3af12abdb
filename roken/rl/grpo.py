"""GRPO for the denoising policy (paper appendix; DeepSeekMath's group-relative advantages, PPO's clipped ratio,
an analytic KL to a frozen reference). Read top to bottom: advantages, the learner's update.

Per group (one prompt, G candidates): A_j = (r_j - mean r) / (std r + eps), all zero when std < min_std (the
group ranks nothing; it is skipped, and counted in rollout/zero_std_frac). Per trained transition
x_k -> x_{k-1} of candidate j:

    ratio = exp(lp_theta - lp_old)                 (mean log-probabilities, roken.rl.policy)
    L_pg  = -min(ratio A_j, clip(ratio, 1 - eps, 1 + eps) A_j)
    L_kl  = ||mu_theta - mu_ref||^2 / (2 sigma_k^2)  (per element, mean over the generated robots)
    L     = mean over transitions and candidates of (L_pg + beta L_kl)

A minibatch is `minibatch_prompts` groups; each group is one forward batch of its G candidates, so its map is
encoded once with gradients (and once for the reference, without).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..model.diffusion import NoiseSchedule
from ..model.dit import RokenDiT
from .config import RLConfig
from .policy import group_prompt, mean_kl, mean_logprob, policy_mean


@dataclass
class Group:
    """One prompt's G candidates as a rollout worker returns them (ARCHITECTURE.md, "RL transitions")."""
    prompt: tuple[int, int]  # (episode index in the bank, time step t): the learner rebuilds the condition
    version: int  # weight version that sampled it
    steps: list[int]  # trained k, descending
    x_k: np.ndarray  # (Kt, G, n, H, 2) float32
    x_prev: np.ndarray  # (Kt, G, n, H, 2)
    logp: np.ndarray  # (Kt, G) log pi_old, mean over the generated elements
    rewards: np.ndarray  # (G,)
    terms: dict = field(default_factory=dict)  # per-candidate reward terms (hard, reach, ...) as (G,) arrays
    worker: str = ""


def group_advantages(rewards: np.ndarray, min_std: float, eps: float = 1e-6) -> np.ndarray:
    """(P, G) rewards -> (P, G) advantages; rows whose std is below min_std are all zero."""
    r = np.asarray(rewards, np.float64)
    std = r.std(axis=1, keepdims=True)
    ok = std >= min_std
    adv = (r - r.mean(axis=1, keepdims=True)) / np.where(ok, std + eps, 1.0)
    return np.where(ok, adv, 0.0).astype(np.float32)


class Learner:
    """The policy, its frozen reference and the optimizer; `update` runs the epochs over one buffer."""

    def __init__(self, policy: RokenDiT, reference: RokenDiT, sched: NoiseSchedule, rc: RLConfig,
                 device: torch.device):
        self.policy, self.ref, self.sched, self.rc, self.device = policy, reference.eval(), sched, rc, device
        for p in self.ref.parameters():
            p.requires_grad_(False)
        # eval mode for the policy too: the sampler ran without dropout, so the ratio starts at exactly 1
        self.policy.eval()
        self.opt = torch.optim.AdamW(policy.parameters(), lr=rc.lr, weight_decay=rc.weight_decay)

    def group_loss(self, g: Group, cond: dict, adv: np.ndarray) -> tuple[torch.Tensor, dict]:
        """The loss of one group (a scalar with gradients) and its statistics."""
        rc, dev = self.rc, self.device
        G = len(adv)
        prompt = group_prompt(self.policy, cond, G, dev)
        with torch.no_grad():
            ref_prompt = group_prompt(self.ref, cond, G, dev)
        A = torch.from_numpy(adv).to(dev)
        total, stats = 0.0, {"policy": 0.0, "kl": 0.0, "approx_kl": 0.0, "clipfrac": 0.0, "ratio_dev": 0.0}
        for j, k in enumerate(g.steps):
            x = torch.tensor(g.x_k[j], device=dev)  # a copy: arrays from Ray are read-only
            x_prev = torch.tensor(g.x_prev[j], device=dev)
            ks = torch.full((G,), k, device=dev, dtype=torch.long)
            sigma = self.sched._at("sigma", ks)
            mean = policy_mean(self.policy, self.sched, prompt, x, ks)
            with torch.no_grad():
                mean_ref = policy_mean(self.ref, self.sched, ref_prompt, x, ks)
            lp = mean_logprob(x_prev, mean, sigma, prompt.generated)
            log_ratio = lp - torch.tensor(g.logp[j], device=dev)
            ratio = log_ratio.exp()
            pg = -torch.min(ratio * A, ratio.clamp(1 - rc.clip, 1 + rc.clip) * A)
            kl = mean_kl(mean, mean_ref, sigma, prompt.generated)
            total = total + (pg + rc.kl_beta * kl).mean()
            with torch.no_grad():
                stats["policy"] += pg.mean().item()
                stats["kl"] += kl.mean().item()
                stats["approx_kl"] += ((ratio - 1) - log_ratio).mean().item()  # CleanRL / Schulman's k3
                stats["clipfrac"] += ((ratio - 1).abs() > rc.clip).float().mean().item()
                stats["ratio_dev"] = max(stats["ratio_dev"], (ratio - 1).abs().max().item())
        n = len(g.steps)
        return total / n, {k: (v if k == "ratio_dev" else v / n) for k, v in stats.items()}

    def update(self, groups: list[Group], conds: list[dict], generator: torch.Generator) -> dict:
        """Epochs of minibatch steps over one on-policy buffer (groups with their conditions), then it is
        discarded. Returns the means of the loss statistics; losses/ratio_dev_first is max |ratio - 1| of the
        first minibatch (0 up to rounding right after a weight sync: a larger value means stale weights)."""
        rc = self.rc
        rewards = np.stack([g.rewards for g in groups])
        adv = group_advantages(rewards, rc.min_std, rc.adv_eps)
        useful = [i for i in range(len(groups)) if np.any(adv[i] != 0)]
        acc = {"policy": [], "kl": [], "approx_kl": [], "clipfrac": [], "grad_norm": []}
        first_dev = None
        self.policy.eval()
        for _ in range(rc.epochs):
            order = [useful[i] for i in torch.randperm(len(useful), generator=generator).tolist()]
            for s in range(0, len(order), rc.minibatch_prompts):
                batch = order[s:s + rc.minibatch_prompts]
                self.opt.zero_grad(set_to_none=True)
                dev_max = 0.0
                for i in batch:
                    loss, st = self.group_loss(groups[i], conds[i], adv[i])
                    (loss / len(batch)).backward()
                    for k in ("policy", "kl", "approx_kl", "clipfrac"):
                        acc[k].append(st[k])
                    dev_max = max(dev_max, st["ratio_dev"])
                if first_dev is None:
                    first_dev = dev_max
                gn = torch.nn.utils.clip_grad_norm_(self.policy.parameters(), rc.grad_clip)
                acc["grad_norm"].append(float(gn))
                self.opt.step()
        out = {f"losses/{'kl_ref' if k == 'kl' else k}": float(np.mean(v)) if v else 0.0 for k, v in acc.items()}
        out["losses/ratio_dev_first"] = float(first_dev or 0.0)
        out["rollout/zero_std_frac"] = 1.0 - len(useful) / max(len(groups), 1)
        out["learner/steps"] = rc.epochs * -(-len(useful) // rc.minibatch_prompts)
        return out
