"""How often does a model's plain sample break a hard constraint in its executed moves, in given visited states?

    python benchmarks/own_state_violations.py --checkpoint runs/sc-base runs/sc-g2 \
        --states runs/ev-sc-base runs/ev-sc-g2 --prompts 256

Plain Roken fails at a per-re-plan hazard (README, "Handing the start to the expert"): one sample whose executed
moves come within d_obs_min of an obstacle or d_coll_min of a team-mate, or leave a robot without a neighbour in
range, ends or dooms the episode. This prints, for each checkpoint and each folder of closed-loop rollouts (an
evaluation folder, a DAgger round's rollouts/), the share of samples (DDIM-10 as the planner samples them, one
per draw) that do so at the rollouts' feasible states (every 8 steps before each first violation; the
`selfcost` term's states, roken/rl/selfcost.py). A model's own rollouts are its closed-loop state distribution;
another model's are the states it was trained on or a fixed yardstick.
"""
from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from roken.config import load_config
from roken.data.condition import decode_chunk
from roken.model.diffusion import COND_KEYS, ddim_sample, make_prompt
from roken.rl.selfcost import SelfCost
from roken.train import checkpoint as ckpt


def rate(loaded, states: str, prompts: int, draws: int, seed: int) -> tuple[float, int]:
    cfg = load_config(None, [f"selfcost.states={states}", "selfcost.weight=1", "selfcost.prompts=32",
                             f"selfcost.candidates={draws}"])
    term = SelfCost(cfg.selfcost, loaded.samples, cfg.plan, cfg.task)
    model, hits, n = loaded.model.eval(), 0.0, 0
    for b in range(-(-prompts // 32)):
        conds, eps = term.prompts(np.random.default_rng([seed, b]))
        batch = {k: torch.from_numpy(np.stack([c[k] for c in conds])) for k in COND_KEYS + ("map", "chunk")}
        gen = torch.Generator().manual_seed(seed * 1000 + b)
        with torch.no_grad():
            prompt = make_prompt(model, {k: batch[k] for k in COND_KEYS + ("map",)}, batch["chunk"], draws)
            chunk = ddim_sample(model, loaded.schedule, prompt, steps=10, generator=gen).chunk.numpy()
        start = np.repeat(np.stack([c["start"] for c in conds]), draws, 0)
        p = torch.from_numpy(decode_chunk(chunk, start, loaded.samples).astype(np.float32))
        real = torch.as_tensor(np.repeat(np.stack([c["robot_mask"] for c in conds]), draws, 0))
        sdf = torch.as_tensor(np.repeat(np.stack([term.fields(e)[0] for e in eps]), draws, 0))
        hits += float(term.violating(p[:, :, :cfg.plan.replan_every], sdf, real).float().sum())
        n += len(p)
    return hits / n, len(term.states)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", nargs="+", required=True, help="checkpoints or run folders")
    ap.add_argument("--states", nargs="+", required=True, help="folders of closed-loop rollouts (comma-joined: one pool)")
    ap.add_argument("--prompts", type=int, default=256, help="visited states drawn per (checkpoint, folder)")
    ap.add_argument("--draws", type=int, default=4, help="samples per state")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_flush_denormal(True)
    print(f"# {platform.processor() or platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} "
          f"thread(s); {args.prompts} states x {args.draws} samples, DDIM-10, the executed moves (2 chunk points)")
    print("| checkpoint | states of | feasible states in the folder | samples violating |")
    print("| --- | --- | --- | --- |")
    t0 = time.perf_counter()
    for c in args.checkpoint:
        loaded = ckpt.load(c, "cpu")
        for s in args.states:
            r, n = rate(loaded, s, args.prompts, args.draws, args.seed)
            print(f"| {c} | {s} | {n} | {r:.3f} |")
    print(f"# {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
