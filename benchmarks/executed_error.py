"""Where in an episode is a model imprecise? The executed-move error at an episode's start against later states.

    python benchmarks/executed_error.py --checkpoint models/roken-cpu-four-dagger runs/pm-a --data data/val4

The training validation's `val/l2_executed_m` averages over prompts cut at a uniform time of held-out expert
episodes. Plain Roken's episodes fail early (the first inter-robot contact at a median of 23-30 simulator steps,
README "The last move as an input"), from a start where the team stands 3-4 m apart. This prints, per checkpoint,
the same figure (mean distance of the first `--executed` sampled chunk points to the expert's, metres, DDIM-10,
one candidate, the task's goal, no given robots) on prompts at t = 0 (the team at rest, as every closed-loop
episode starts), at t = 4..15 (the first re-plans) and at a uniform t, with the first-move cosine of the
followers and the executed move's length against the expert's.

    python benchmarks/executed_error.py --checkpoint runs/fitm16 --data data/fit16m --levels

`--levels` adds, per checkpoint, where in the diffusion chain the error arises, on prompts drawn as training
draws them (the dataset's own chunk windows: t = 0 of Markov-label continuations, the push window of DART
episodes, uniform t otherwise): the executed points' error of the one-step clean-chunk estimate x0_hat(x_k) from
the label noised to level k, and of DDIM-10 started from the label noised to the level of its i-th step instead of
from pure noise (from k = 99: the plain sample). A denoiser that had fit its labels would return them from every
level; the error it leaves at low k is the precision no sampler setting can recover.
"""
from __future__ import annotations

import argparse
import platform
import time
from dataclasses import replace

import numpy as np
import torch

from roken.data.loader import collate
from roken.data.samples import EpisodeBank, make_sample
from roken.model.diffusion import COND_KEYS, ddim_sample, ddim_steps, make_prompt
from roken.plan.planner import RokenPlanner

LEVELS = (0, 11, 22, 33, 44, 55, 66, 77, 88)


def prompts(bank: EpisodeBank, cfg, count: int, t_range: tuple[int, int] | None, seed: int) -> list[dict]:
    """`count` full-team prompts with the task's goal at times drawn in t_range (None: uniform over the episode)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in rng.choice(len(bank), size=count, replace=count > len(bank)):
        T = int(bank.num_steps[i])
        if t_range is None:
            bank.sample_until = None
        else:
            lo, hi = t_range
            if T <= hi:
                continue
            bank.sample_until = np.full(len(bank), hi + 1)
        s = make_sample(bank, int(i), np.random.default_rng(int(rng.integers(1 << 31))), cfg)
        if t_range is not None and t_range[0] > 0:  # make_sample draws t in [0, hi]; keep those in range
            P = bank.positions(int(i))
            t = int(np.flatnonzero(np.abs(P - s["start"][:len(P[0])]).max(axis=(1, 2)) == 0)[0])
            if t < t_range[0]:
                continue
        out.append(s)
    bank.sample_until = None
    return out


def measure(planner: RokenPlanner, batch: list[dict], executed: int, seed: int) -> dict[str, float]:
    gen = [torch.Generator().manual_seed(seed + k) for k in range(len(batch))]
    plans = planner.sample(batch, 1, "ddim", 10, gen)[:, 0]  # (B, T, H, 2) metres
    cfg = planner.cfg
    l2, cos, ratio = [], [], []
    for s, p in zip(batch, plans):
        n = int(s["num_robots"])
        start = s["start"][:n]
        expert = start[:, None] + np.cumsum(s["chunk"][:n], axis=1) * cfg.step_scale  # (n, H, 2)
        l2.append(np.linalg.norm(p[:n, :executed] - expert[:, :executed], axis=-1).mean())
        m, e = p[:n, 0] - start, expert[:, 0] - start
        ok = (np.linalg.norm(e, axis=-1) >= 0.05) & (s["goal_mask"][:n] == 0)
        if ok.any():
            cos.extend((m[ok] * e[ok]).sum(-1) / (np.linalg.norm(m[ok], axis=-1) * np.linalg.norm(e[ok], axis=-1) + 1e-9))
            ratio.extend(np.linalg.norm(m[ok], axis=-1) / np.linalg.norm(e[ok], axis=-1))
    return {"l2": float(np.mean(l2)), "cos_f": float(np.mean(cos)) if cos else np.nan,  # (a small last batch may
            "len_ratio": float(np.median(ratio)) if ratio else np.nan, "n": len(batch)}  # hold no moving follower)


@torch.no_grad()
def levels(planner: RokenPlanner, bank: EpisodeBank, cfg, count: int, executed: int, seed: int) -> tuple[list, list]:
    """[(k, error of x0_hat(x_k), of eps_hat = 0)], [(k, error of DDIM-10 from x_k)]: executed points, metres."""
    rng = np.random.default_rng(seed)
    b = collate([make_sample(bank, int(i), np.random.default_rng(int(rng.integers(1 << 31))), cfg)
                 for i in rng.choice(len(bank), size=count, replace=count > len(bank))])
    model, S = planner.model, planner.schedule
    cond = {k: b[k] for k in COND_KEYS if k in b} | {"map": b["map"]}
    x0, real = b["chunk"], b["robot_mask"].float()
    eps = torch.randn(x0.shape, generator=torch.Generator().manual_seed(seed))
    ctx = model.encode_map(b["map"])

    def err(c: torch.Tensor) -> float:  # executed points of chunk c against the label's, metres
        d = torch.cumsum(c - x0, dim=2)[:, :, :executed].norm(dim=-1).mean(-1) * cfg.step_scale  # (B, R)
        return float((d * real).sum() / real.sum())

    def noised(k: int) -> tuple[torch.Tensor, torch.Tensor]:
        ks = torch.full((len(x0),), k)
        return S.q_sample(x0, ks, eps), ks

    one = []  # (k, the model's estimate, the noise a zero estimate eps_hat = 0 keeps: the scale of the level)
    for k in LEVELS:
        xk, ks = noised(k)
        one.append((k, err(S.predict_x0(xk, ks, S.eps_from(model(xk, ks, cond, ctx=ctx)["eps"], xk, ks))),
                    err(S.predict_x0(xk, ks, torch.zeros_like(xk)))))
    seq, chain = ddim_steps(S.K, 10), []
    prompt = make_prompt(model, cond, x0, ctx=ctx)
    for j in sorted({0, 3, 6, len(seq) - 2, len(seq) - 1}):  # deterministic DDIM (eta = 0), as the planner samples
        chain.append((seq[j], err(ddim_sample(model, S, prompt, 10, start=j, latent=noised(seq[j])[0]).chunk)))
    return one, chain


def _average(values: list[float], weights: np.ndarray) -> float:
    """The prompt-weighted mean of per-batch figures, over the batches that have one."""
    v = np.asarray(values, float)
    ok = ~np.isnan(v)
    return float(np.average(v[ok], weights=weights[ok])) if ok.any() else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", nargs="+", required=True)
    ap.add_argument("--data", default="data/val4", help="held-out expert episodes (a dataset folder)")
    ap.add_argument("--prompts", type=int, default=256)
    ap.add_argument("--executed", type=int, default=2, help="chunk points the closed loop executes (replan_every)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--levels", action="store_true", help="also the error at each noise level (see above)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    bank = EpisodeBank.from_folder(args.data)
    windows = bank.sample_until
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, one thread; "
          f"{args.data}: {len(bank)} episodes, {args.prompts} prompts per row, DDIM-10, 1 candidate\n")
    print("| checkpoint | prompts at | executed L2 (m) | 1st-move cos follower | 1st-move length / expert's (median) |")
    print("| --- | --- | --- | --- | --- |")
    for path in args.checkpoint:
        planner = RokenPlanner.load(path, "cpu")
        cfg = replace(planner.cfg, augment=False, shuffle_robots=False, final_goal_prob=1.0, condition_prob=0.0, subteam_prob=0.0,
                      prev_noise=0.0, early_prob=0.0)
        t0 = time.perf_counter()
        for label, rng_t in (("t = 0 (at rest)", (0, 0)), ("t = 4..15", (4, 15)), ("uniform t", None)):
            batch = prompts(bank, cfg, args.prompts, rng_t, args.seed)
            rows = [measure(planner, batch[k:k + 64], args.executed, args.seed + k) for k in range(0, len(batch), 64)]
            w = np.array([r["n"] for r in rows], float)
            avg = {k: _average([r[k] for r in rows], w) for k in ("l2", "cos_f", "len_ratio")}
            print(f"| {path} | {label} ({int(w.sum())}) | {avg['l2']:.3f} | {avg['cos_f']:.3f} | {avg['len_ratio']:.2f} |")
        print(f"<!-- {path}: {time.perf_counter() - t0:.0f} s -->")
        if args.levels:
            bank.sample_until = windows  # the dataset's own chunk windows (prompts() clears them)
            one, chain = levels(planner, bank, cfg, args.prompts, args.executed, args.seed)
            bank.sample_until = None
            print(f"\n{path}, {args.prompts} training-window prompts: executed-point error (m) of x0_hat(x_k), "
                  f"and of DDIM-10 from the label noised to k\n")
            print("| k | " + " | ".join(str(k) for k, _, _ in one) + " |\n|" + " --- |" * (len(one) + 1))
            print("| x0_hat(x_k) | " + " | ".join(f"{e:.3f}" for _, e, _ in one) + " |")
            print("| (eps_hat = 0) | " + " | ".join(f"{e:.3f}" for _, _, e in one) + " |")
            print("\n| DDIM-10 from k | " + " | ".join(str(k) for k, _ in chain) + " |\n|" + " --- |" * (len(chain) + 1))
            print("| executed L2 | " + " | ".join(f"{e:.3f}" for _, e in chain) + " |\n")


if __name__ == "__main__":
    main()
