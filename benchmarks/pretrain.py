"""Pretraining throughput: the training step per preset, the two data paths against what the model consumes,
and Ray Train parallel efficiency with 1 vs 2 CPU workers.

    python benchmarks/pretrain.py --data data/train200                    # everything, CPU
    python benchmarks/pretrain.py --data data/train200 --only step --presets paper --device cuda --compile
    python benchmarks/pretrain.py --data data/train200 --only ray --ray-preset small

step   optimizer steps/s x batch on pre-made batches (forward, backward, clip, AdamW, EMA; no data loading),
       fp32 on CPU, bf16 autocast on CUDA
data   samples/s of the per-worker DataLoader (SampleStream, 0..2 loader processes) and of Ray Data
       (read_parquet -> map_batches(EpisodeBatchToSamples) -> iter_torch_batches)
draws  draws/s per core (decoder rows: samples x train.noise_draws) of the `small` preset at K = 1, 4, 8, 16,
       of the laptop encoder options, and of the shipped recipe (configs/pretrain/cpu.yaml), one thread each;
       ends with `recipe speed-up vs small K=1: X.XXx`
ray    pipelines/pretrain.py on a --local cluster with 1 and 2 workers at the same per-worker batch (weak
       scaling); steady samples/s from metrics.jsonl, parallel efficiency = rate(2) / (2 rate(1))
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from roken.config import load_config
from roken.data.loader import EpisodeBatchToSamples, collate
from roken.model.dit import preset
from roken.train.data import SampleStream, load_banks, make_loader
from roken.train.loop import Pretraining, PretrainSpec

ROOT = Path(__file__).resolve().parents[1]


def bench_step(data: str, name: str, batch: int, device: str, compile_: bool, steps: int,
               extra: list[str] | None = None, config: str | None = None) -> float:
    """Samples/s of optimizer steps on one pre-made batch (no data loading)."""
    pre = [] if name is None else [f"model.{k}={v}" for k, v in preset(name).__dict__.items()]
    cfg = load_config(config, pre + [f"train.batch_size={batch}", f"train.device={device}",
                                     f"train.compile={compile_}", "train.val_fraction=0"] + (extra or []))
    run = Pretraining(PretrainSpec.of(cfg), data, tempfile.mkdtemp(prefix="bench-"))
    run._build()
    stream = SampleStream(run.train_bank, cfg.samples)
    b = {k: v.to(run.device) for k, v in collate([stream[g] for g in range(batch)]).items()}
    for _ in range(3):
        run.train_step(b)
    if run.device.type == "cuda":
        torch.cuda.synchronize()
    t = time.perf_counter()
    for _ in range(steps):
        logs = run.train_step(b)
    float(logs["losses/total"])  # waits for the device
    return steps * batch / (time.perf_counter() - t)


def bench_draws(data: str, steps: int) -> None:
    """Draws/s per core (one thread): K noise draws per encoded sample, the encoders, the shipped recipe."""
    torch.set_num_threads(1)
    print("\n| variant | batch x K | draws/s per core |\n| --- | --- | --- |")
    rows = [("small K=1", "small", 32, ["train.noise_draws=1"], None)]
    rows += [(f"small K={k}", "small", 32 // min(k, 8), [f"train.noise_draws={k}"], None) for k in (4, 8, 16)]
    rows += [("small patch encoder K=1", "small", 32, ["model.map_encoder=patch"], None)]
    rows += [(f"small patch encoder + crop K={k}", "small", 32 // min(k, 8),
              ["model.map_encoder=patch", "model.local_crop=9", f"train.noise_draws={k}"], None) for k in (1, 4, 8, 16)]
    rows += [("shipped recipe (configs/pretrain/cpu.yaml)", None, None, [], str(ROOT / "configs/pretrain/cpu.yaml"))]
    rates = {}
    for label, name, batch, extra, config in rows:
        if config is not None:
            from roken.config import load_config as _lc
            c = _lc(config, [])
            batch, k = c.train.batch_size, c.train.noise_draws
        else:
            k = int(next(x for x in extra + ["train.noise_draws=1"] if x.startswith("train.noise_draws")).split("=")[1])
        rates[label] = bench_step(data, name, batch, "cpu", False, steps, extra, config) * k
        print(f"| {label} | {batch} x {k} | {rates[label]:.0f} |", flush=True)
    print(f"recipe speed-up vs small K=1: {rates[rows[-1][0]] / rates['small K=1']:.2f}x")


def bench_loader(data: str, workers: int, batch: int, batches: int) -> float:
    cfg = load_config(None, [])
    bank, _, _ = load_banks(data, cfg.samples.canvas)
    for m in range(len(bank.map_ids)):  # steady state: every map's SDF is computed once per run and kept
        bank.sdf(m)
    loader = make_loader(SampleStream(bank, cfg.samples), 0, batches + 2, batch, 0, 1, workers)
    it = iter(loader)
    next(it), next(it)  # start-up (worker processes, first SDFs)
    t = time.perf_counter()
    for _ in range(batches):
        next(it)
    return batches * batch / (time.perf_counter() - t)


def bench_ray_data(data: str, batch: int, batches: int) -> float:
    from roken import ray_pool

    ray_pool.connect(local=True)
    cfg = load_config(None, [])
    ds = ray_pool.read_ray_dataset(data).map_batches(EpisodeBatchToSamples(data, cfg.samples), batch_format="numpy",
                                                     batch_size=64)
    it = iter(ds.iter_torch_batches(batch_size=batch, local_shuffle_buffer_size=4 * batch))
    next(it)
    t = time.perf_counter()
    n = 0
    for _ in range(batches):
        try:
            n += len(next(it)["chunk"])
        except StopIteration:
            break
    rate = n / (time.perf_counter() - t)
    del it, ds  # release the stream's objects before the cluster goes
    import ray
    ray.shutdown()
    return rate


def bench_ray_train(data: str, name: str, per_worker: int, steps: int, workers: int) -> float:
    out = tempfile.mkdtemp(prefix="bench-ray-")
    cmd = [sys.executable, str(ROOT / "pipelines" / "pretrain.py"), "--data", data, "--out", out, "--preset", name,
           "--steps", str(steps), "--batch-size", str(per_worker * workers), "--local", "--num-cpus", str(workers),
           "--workers", str(workers), "--set", "train.loader_workers=0", "--set", "train.eval_every=0",
           "--set", "train.val_fraction=0", "--set", "train.log_every=5", "--set", f"train.checkpoint_every={steps}"]
    subprocess.run(cmd, check=True, capture_output=True, timeout=1800, env=dict(os.environ, OMP_NUM_THREADS="1"))
    rows = [json.loads(x) for x in (Path(out) / "metrics.jsonl").read_text().splitlines()]
    steady = [r["charts/samples_per_s"] for r in rows[1:]]  # the first window holds start-up
    return sum(steady) / len(steady)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--only", choices=("step", "data", "ray", "draws"))
    ap.add_argument("--presets", default="tiny,small,paper")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--ray-preset", default="small")
    ap.add_argument("--ray-steps", type=int, default=40)
    args = ap.parse_args()
    torch.set_flush_denormal(True)
    print(f"machine: {os.cpu_count()} cores, torch {torch.__version__}, {torch.get_num_threads()} threads")
    if args.only in (None, "step"):
        print("\n| preset | batch | device | train samples/s |\n| --- | --- | --- | --- |")
        for name in args.presets.split(","):
            rate = bench_step(args.data, name, args.batch, args.device, args.compile, args.steps)
            print(f"| {name} | {args.batch} | {args.device}{' compiled' if args.compile else ''} | {rate:.1f} |")
    if args.only in (None, "draws"):
        bench_draws(args.data, args.steps)
    if args.only in (None, "data"):
        print("\n| data path | samples/s |\n| --- | --- |")
        for w in (0, 1, 2):
            print(f"| DataLoader, {w} loader processes | {bench_loader(args.data, w, 128, 8):.0f} |")
        print(f"| Ray Data map_batches + iter_torch_batches | {bench_ray_data(args.data, 128, 8):.0f} |")
    if args.only in (None, "ray"):
        one = bench_ray_train(args.data, args.ray_preset, 32, args.ray_steps, 1)
        two = bench_ray_train(args.data, args.ray_preset, 32, args.ray_steps, 2)
        print(f"\n| Ray Train workers | preset | per-worker batch | samples/s |\n| --- | --- | --- | --- |\n"
              f"| 1 | {args.ray_preset} | 32 | {one:.1f} |\n| 2 | {args.ray_preset} | 32 | {two:.1f} |\n"
              f"parallel efficiency 1 -> 2 workers: {two / (2 * one):.2f}")


if __name__ == "__main__":
    main()
