"""Train variants for the same budget and compare them in closed loop on the same `val` tasks.

    python pipelines/ablate.py --data data/train4 --val-data data/val4 --out runs/abl \\
        --variants configs/ablate/levers.yaml --config configs/pretrain/cpu.yaml --minutes 5 --workers 0
    python pipelines/ablate.py ... --local --workers 2 --threads 1      # one variant per Ray actor

Writes OUT/variants/NAME/ (each variant's run folder: checkpoints, metrics.jsonl, result.json),
OUT/ablation.json (one object per variant: name, overrides, steps, cpu_seconds, success, reach,
obstacle_collision, inter_collision, connectivity, first_move_cos_follower, ...), OUT/ablation.md (the table)
and OUT/ablation.png (closed-loop success vs CPU minutes, one line per variant). The same command resumes:
finished variants are skipped, an interrupted one continues from its last checkpoint.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from common import USER_ERRORS, add_common_args, fail, make_runner

from roken.config import load_config
from roken.model.dit import PRESETS, preset
from roken.train import ablation
from roken.train.data import check_dataset
from roken.train.loop import check_sections
from roken.units import Unit


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="training dataset (pipelines/generate.py --maps train)")
    ap.add_argument("--val-data", help="validation dataset (pipelines/generate.py --maps val); default: "
                                       "train.val_fraction of --data's maps")
    ap.add_argument("--out", required=True, help="ablation folder")
    ap.add_argument("--variants", required=True, help="YAML file with a `variants:` list (configs/ablate/)")
    budget = ap.add_mutually_exclusive_group(required=True)
    budget.add_argument("--minutes", type=float, help="training minutes per variant (validation excluded)")
    budget.add_argument("--steps", type=int, help="optimizer steps per variant")
    ap.add_argument("--preset", choices=sorted(PRESETS), help="model size for every variant (before its overrides)")
    ap.add_argument("--episodes", type=int, default=32, help="closed-loop val tasks per evaluation (default 32)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads per variant (default: torch's)")
    add_common_args(ap)
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        if (args.minutes is not None and args.minutes <= 0) or (args.steps is not None and args.steps < 1):
            raise ValueError("--minutes must be > 0 and --steps >= 1")
        if args.episodes < 1:
            raise ValueError(f"--episodes {args.episodes}: must be >= 1")
        variants = ablation.load_variants(args.variants)
        base = ([f"model.{k}={v}" for k, v in preset(args.preset).__dict__.items()] if args.preset else []) \
            + list(args.set or []) + ablation.budget_overrides(args.minutes, args.steps, args.episodes)
        data, val = os.path.abspath(args.data), args.val_data and os.path.abspath(args.val_data)
        check_dataset(data, "--data")
        if val:
            check_dataset(val, "--val-data")
        units = []
        for v in variants:
            sets = base + v["overrides"]
            try:  # every variant's config is checked before anything runs
                check_sections(load_config(args.config, sets))
            except ValueError as e:
                raise ValueError(f"--variants {args.variants}: variant {v['name']!r}: {e}") from None
            units.append(Unit(v["name"], {"name": v["name"], "overrides": sets, "variant_overrides": v["overrides"]}))
        out = Path(args.out).resolve()
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {out}: is a file; the ablation writes a folder there")
        config = args.config and os.path.abspath(args.config)
        todo = [u for u in units if ablation.finished(out, u.key, u.payload["overrides"], config) is None]
        print(f"[ablate] {len(units)} variants, {len(units) - len(todo)} finished earlier; budget "
              f"{f'{args.minutes:g} min' if args.minutes else f'{args.steps} steps'} each, {args.episodes} "
              f"closed-loop val tasks", file=sys.stderr)
        rows = {}
        if todo:
            runner = make_runner(args)
            ctx = {"out": str(out), "data": data, "val_data": val, "config": config, "threads": args.threads}
            print(f"[ablate] running on {runner.describe()}", file=sys.stderr)
            failed = []
            for k, r in enumerate(runner.imap_unordered("roken.train.ablation:run_variant", ctx, todo), 1):
                if r.ok:
                    rows[r.unit.key] = r.value
                    print(f"[ablate] {k}/{len(todo)} {r.unit.key}: success {r.value['success']:.3f} reach "
                          f"{r.value['reach']:.3f} ({r.seconds / 60:.1f} min; elapsed "
                          f"{(time.perf_counter() - t0) / 60:.1f} min)", file=sys.stderr)
                else:
                    failed.append(f"{r.unit.key}: {r.error}")
            runner.shutdown()
            if failed:
                print("[ablate] failed (re-run the same command to retry them):\n  " + "\n  ".join(failed),
                      file=sys.stderr)
        for u in units:
            rows.setdefault(u.key, ablation.finished(out, u.key, u.payload["overrides"], config))
        done = [rows[u.key] for u in units if rows.get(u.key)]
        budget = f"{args.minutes:g} training minutes" if args.minutes else f"{args.steps} steps"
        ablation.write_report(out, done, f"Budget: {budget} per variant; closed loop on {args.episodes} `val` "
                                         f"tasks (4 robots, plain Roken). Base overrides: {' '.join(base)}")
    except USER_ERRORS as e:
        return fail(e)
    print(ablation.table(done))
    print(f"wrote {out / 'ablation.json'}, {out / 'ablation.md'}, {out / 'ablation.png'}")
    return 0 if len(done) == len(units) else 1


if __name__ == "__main__":
    sys.exit(main())
