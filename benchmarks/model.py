"""Roken DiT throughput and latency: parameters, training samples/s (forward + backward), plan latency.

    python benchmarks/model.py --preset paper                      # CPU, all threads
    python benchmarks/model.py --preset small --threads 2
    python benchmarks/model.py --preset paper --device cuda --dtype bf16 --compile

A plan = encode the map once, then denoise all robots' chunks (DDPM-100 or DDIM-10) for 1 or 32 candidates in
one batch; latency is the median over repeats after warm-up. Inputs are a generated map with random starts
(the network's cost does not depend on the values). Also prints where a plan's time goes: map encoding vs one
denoising step.
"""
from __future__ import annotations

import argparse
import statistics
import time
from contextlib import nullcontext

import numpy as np
import torch

from roken.data.condition import build_condition
from roken.data.samples import SampleConfig
from roken.model.diffusion import COND_KEYS, DiffusionConfig, NoiseSchedule, ddim_sample, ddpm_sample, make_prompt
from roken.model.dit import PRESETS, RokenDiT, preset
from roken.model.losses import LossConfig, pretraining_loss
from roken.world.maps import MapConfig, generate_map


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def timed(fn, device, repeat: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    sync(device)
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        sync(device)
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def make_cond(n: int, R: int, device, rng) -> dict:
    """A plan's inputs for n robots on a generated map, through the one condition builder."""
    occ = generate_map(MapConfig(), "eval", 0).occupancy
    free = np.argwhere(occ == 0)
    starts = free[rng.choice(len(free), size=n, replace=False)][:, ::-1] + 0.5  # (x, y)
    goal = free[rng.integers(len(free))][::-1] + 0.5
    cond = build_condition(occ, starts, 0, goal, SampleConfig(), tokens=R)
    return {k: torch.from_numpy(np.asarray(cond[k])[None]).to(device) for k in COND_KEYS + ("map",)}


def train_batch(B: int, device, rng) -> dict:
    R, H, K = 10, 16, 5
    n = rng.integers(2, 9, size=B)
    robot_mask = np.arange(R)[None] < n[:, None]
    occ = generate_map(MapConfig(), "eval", 1).occupancy.astype(np.float32)
    batch = {
        "chunk": rng.uniform(-0.7, 0.7, (B, R, H, 2)), "start": rng.uniform(20, 120, (B, R, 2)),
        "rel_goal": rng.normal(size=(B, R, 2)), "goal_mask": (np.arange(R)[None] == 0).repeat(B, 0),
        "traj_mask": np.zeros((B, R)), "robot_mask": robot_mask, "waypoints": rng.normal(size=(B, R, K, 2)) * 0.3,
        "occ_small": rng.random((B, R, 7, 7)) < 0.3, "occ_large": rng.random((B, R, 7, 7)) < 0.3,
        "map": np.repeat(occ[None, None], 3, axis=1).repeat(B, 0), "sdf": rng.normal(size=(B, 140, 140)) * 5,
    }
    out = {k: torch.as_tensor(v, dtype=torch.bool if k == "robot_mask" else torch.float32) for k, v in batch.items()}
    return {k: v.to(device) for k, v in out.items()}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="small", choices=sorted(PRESETS))
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--dtype", default="fp32", choices=["fp32", "bf16"], help="bf16 = autocast")
    p.add_argument("--compile", action="store_true", help="torch.compile the decoder blocks")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch default)")
    p.add_argument("--train-batch", type=int, default=0, help="default: 32 on CPU, 128 on GPU (paper)")
    p.add_argument("--repeat", type=int, default=0, help="timed repeats (default 5 on CPU, 20 on GPU)")
    p.add_argument("--robots", default="4,10")
    p.add_argument("--skip-ddpm", action="store_true", help="DDIM-10 only (DDPM-100 is 10x longer)")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    device = torch.device(a.device)
    repeat = a.repeat or (20 if device.type == "cuda" else 5)
    amp = torch.autocast(device.type, dtype=torch.bfloat16) if a.dtype == "bf16" else nullcontext()
    rng = np.random.default_rng(0)
    model = RokenDiT(preset(a.preset)).to(device)
    if a.compile:
        for blk in model.blocks:
            blk.compile(dynamic=False)
    sched = NoiseSchedule(DiffusionConfig(num_steps=100), device)
    print(f"preset: {a.preset}  device: {device}  dtype: {a.dtype}  compile: {a.compile}  "
          f"threads: {torch.get_num_threads()}")
    print(f"params: {model.num_params()}")

    B = a.train_batch or (128 if device.type == "cuda" else 32)
    batch = train_batch(B, device, rng)
    opt = torch.optim.AdamW(model.parameters(), lr=5e-4)

    def step():
        with amp:
            loss, _ = pretraining_loss(model, sched, batch, LossConfig(), SampleConfig())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    t = timed(step, device, max(3, repeat // 2))
    print(f"train: batch {B}, {t * 1e3:.1f} ms/step, {B / t:.0f} samples/s (forward + backward + AdamW, full loss)")

    model.eval()
    rows = []
    for n in [int(x) for x in a.robots.split(",")]:
        cond = make_cond(n, n, device, rng)  # exactly n robot tokens at inference: no padding needed
        with torch.no_grad(), amp:
            enc = timed(lambda: model.encode_map(cond["map"]), device, repeat)
            prompt1 = make_prompt(model, cond, num_candidates=1)
            x = torch.randn(1, n, 16, 2, device=device)
            k = torch.zeros(1, dtype=torch.long, device=device)
            step1 = timed(lambda: model(x, k, prompt1.cond, ctx=prompt1.ctx), device, repeat)
        rows.append((n, "map encoding", 1, enc))
        rows.append((n, "one denoising step", 1, step1))
        for G in (1, 32):
            for name, fn in (("DDIM-10", lambda pr: ddim_sample(model, sched, pr, steps=10)),
                             ("DDPM-100", lambda pr: ddpm_sample(model, sched, pr))):
                if name == "DDPM-100" and a.skip_ddpm:
                    continue

                def plan():
                    with torch.no_grad(), amp:
                        return fn(make_prompt(model, cond, num_candidates=G)).chunk

                rows.append((n, name, G, timed(plan, device, repeat if name == "DDIM-10" else max(2, repeat // 4))))
    print(f"{'robots':>6}  {'what':<20} {'candidates':>10}  {'ms / plan':>10}")
    for n, name, G, t in rows:
        print(f"{n:>6}  {name:<20} {G:>10}  {t * 1e3:>10.1f}")


if __name__ == "__main__":
    main()
