"""Pretrain the Roken DiT on an expert dataset: in-process, or Ray Train (DDP) on a laptop or a cluster.

    python pipelines/pretrain.py --data data/train --out runs/pre --config configs/pretrain/laptop.yaml --workers 0
    python pipelines/pretrain.py --data data/train --out $PWD/runs/pre --config configs/pretrain/mixed.yaml \
        --local --workers 2
    ray job submit --runtime-env cluster/runtime_env.yaml --working-dir . -- \\
        python pipelines/pretrain.py --data /shared/train --out /shared/runs/mixed \\
        --config configs/pretrain/mixed.yaml --workers 4 --gpus-per-worker 1

Writes OUT/checkpoint-NNNNNNN/ (model.safetensors with the EMA weights, config.json, train_state.pt),
OUT/metrics.jsonl, TensorBoard files under OUT/tb and OUT/summary.json. Running the same command again on
the same --out resumes from the latest checkpoint; a different model / loss / sample config there is refused.
`--workers 0` runs the loop in this process without Ray (a GPU box without Ray, debugging).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from common import (ROOT, USER_ERRORS, absolute, add_common_args, fail, interrupted, local_run_folder,
                    named_overrides, selfcost_states, wants_ray)

from roken.config import Config, load_config
from roken.configtools import to_dict
from roken.data.build import changed_keys
from roken.data.store import StoreError
from roken.model.dit import PRESETS, preset
from roken.train import checkpoint as ckpt
from roken.train.data import check_dataset
from roken.train.loop import Pretraining, PretrainSpec, summary_table

# Sections that must match to resume a run; train.steps and the logging cadence may change (extend a run).
RESUME_SECTIONS = ("model", "diffusion", "samples", "loss", "selfcost")
RESUME_TRAIN_KEYS = ("batch_size", "lr", "weight_decay", "warmup_steps", "schedule", "min_lr_ratio", "grad_clip",
                     "ema_decay", "seed", "val_fraction")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="dataset folder or URI from pipelines/generate.py; several, "
                                                  "comma-separated, are mixed (see --data-shares)")
    ap.add_argument("--data-shares", help="with several --data: each one's share of the training samples, "
                                          "comma-separated (e.g. 0.5,0.5); default: in proportion to their episodes")
    ap.add_argument("--out", required=True, help="run folder (checkpoints, metrics); an absolute path for Ray")
    ap.add_argument("--val-data", help="held-out dataset (generated with --maps val; a dataset of eval maps is "
                                       "refused); default: train.val_fraction of --data's maps")
    ap.add_argument("--init", help="start a new run from this checkpoint's weights, EMA and optimizer state "
                                   "(fine-tuning; its step is not taken: train.steps counts from 0)")
    ap.add_argument("--preset", choices=sorted(PRESETS), help="model size (sets the model section over --config)")
    ap.add_argument("--steps", type=int, help="optimizer steps (train.steps)")
    ap.add_argument("--batch-size", type=int, help="global batch (train.batch_size), split over the workers")
    ap.add_argument("--device", help="auto (CUDA where available), cpu or cuda (train.device)")
    ap.add_argument("--gpus-per-worker", type=float, default=0.0, help="GPUs per Ray Train worker (0 = CPU, gloo)")
    ap.add_argument("--cpus-per-worker", type=float, default=1.0, help="CPUs per Ray Train worker")
    ap.add_argument("--max-failures", type=int, default=3, help="worker-group restarts from the last checkpoint")
    add_common_args(ap)
    return ap


def overrides(args) -> list[str]:
    pre = [f"model.{k}={v}" for k, v in asdict(preset(args.preset)).items()] if args.preset else []
    renamed = argparse.Namespace(set=args.set, steps=args.steps, batch_size=args.batch_size, device=args.device)
    return pre + named_overrides(renamed, "train", ("steps", "batch_size", "device"))


def datasets(data: str, shares: str | None) -> tuple[list[str], list[float] | None]:
    """--data and --data-shares as (absolute locations, shares or None), checked before anything is written."""
    locations = [absolute(d.strip()) for d in data.split(",") if d.strip()]
    if not shares:
        return locations, None
    try:
        values = [float(x) for x in shares.split(",")]
    except ValueError:
        values = []
    if len(values) != len(locations) or any(v < 0 for v in values) or sum(values) <= 0:
        raise ValueError(f"--data-shares {shares}: give one share >= 0 per --data folder ({len(locations)}), with a "
                         f"positive total, e.g. --data-shares {','.join(['0.5'] * len(locations))}")
    return locations, values


def check_resume(out: str, cfg) -> int:
    """The step an existing run folder resumes from (0 if none); refuses a run made with another config."""
    if not Path(out).is_dir():
        return 0
    found = ckpt.list_checkpoints(out)
    if not found:
        return 0
    old = ckpt.read_config(found[-1])
    new = to_dict(cfg)
    defaults = json.loads(json.dumps(to_dict(Config()), default=str))  # options newer than the run: their defaults
    changed = []
    for sec in RESUME_SECTIONS:
        changed += changed_keys(defaults[sec] | old.get(sec, {}), json.loads(json.dumps(new[sec], default=str)),
                                sec + ".")
    changed += changed_keys({k: old.get("train", {}).get(k) for k in RESUME_TRAIN_KEYS},
                             {k: new["train"][k] for k in RESUME_TRAIN_KEYS}, "train.")
    if changed:
        raise StoreError(f"{out} holds a run made with a different config ({'; '.join(changed[:6])}); its "
                         f"checkpoints are kept. Use a new --out, or the old settings to resume it")
    return int(old.get("step", 0))


def run_ray(args, cfg, out: str) -> None:
    from roken import ray_pool, ray_train

    resources = ray_pool.connect(args.address, args.local, args.num_cpus, code_root=str(ROOT), dashboard=True)
    workers = args.workers or max(1, int(resources.get("GPU", 0) // max(args.gpus_per_worker, 1))
                                  if args.gpus_per_worker else 1)
    print(f"[pretrain] Ray Train: {workers} worker(s) x (CPU {args.cpus_per_worker}, GPU {args.gpus_per_worker}); "
          f"global batch {cfg.train.batch_size} = {cfg.train.batch_size // workers} per worker", file=sys.stderr)
    ray_train.fit(ray_train.pretrain_worker, {"config": to_dict(cfg), "data": args.data, "out": out,
                                          "val_data": args.val_data, "init": args.init, "root": str(ROOT),
                                          "shares": args.shares},
                  out, workers, args.cpus_per_worker, args.gpus_per_worker, args.max_failures,
                  cfg.train.keep_checkpoints)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    out, run = args.out, None
    try:
        cfg = load_config(args.config, overrides(args))
        out = local_run_folder(args.out, "pretraining", "run folder (a new or an existing run)")
        args.data, args.shares = datasets(args.data, args.data_shares)
        args.val_data = absolute(args.val_data)
        selfcost_states(cfg)
        if args.init:
            # a bad checkpoint fails here, before any write; absolute, since Ray workers run elsewhere
            args.init = str(ckpt.find(args.init).resolve())
            ckpt.same_diffusion(args.init, cfg.diffusion)
        for d, role in [(d, "--data") for d in args.data] + [(args.val_data, "--val-data")]:
            if d:
                check_dataset(d, role)
        args.data = args.data[0] if len(args.data) == 1 else args.data
        step = check_resume(out, cfg)
        done = Path(out) / "summary.json"
        last = json.loads(done.read_text()) if step and done.is_file() else None
        budget = cfg.train.time_budget_s
        if last and last.get("steps") == step and (step >= cfg.train.steps or budget > 0 and
                                                    last.get("train_s", 0.0) >= budget):
            print(f"[pretrain] {out} is finished (step {step} of train.steps={cfg.train.steps}); raise --steps "
                  f"(or train.time_budget_s) to train on. Its summary:", file=sys.stderr)
            print(summary_table(last))
            return 0
        if wants_ray(args):
            run_ray(args, cfg, out)
        else:
            run = Pretraining(PretrainSpec.of(cfg), args.data, out, args.val_data, data_shares=args.shares,
                              init=args.init)
            run.fit()
        summary = json.loads((Path(out) / "summary.json").read_text())
    except USER_ERRORS as e:
        return fail(e)
    except KeyboardInterrupt:
        return interrupted("pretrain", out, getattr(run, "step", None))
    print(summary_table(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
