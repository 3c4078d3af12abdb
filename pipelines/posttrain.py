"""Post-train a Roken checkpoint with GRPO: rollout workers sample candidate groups, the learner (this process)
updates the policy against a frozen copy of the pretrained model.

    python pipelines/posttrain.py --checkpoint models/roken-small-mixed --data data/train --out runs/grpo \\
        --config configs/posttrain/laptop.yaml --workers 0
    python pipelines/posttrain.py --checkpoint runs/pre --data data/train --out $PWD/runs/grpo --local --workers 2
    ray job submit --working-dir . -- python pipelines/posttrain.py --checkpoint /shared/runs/mixed \\
        --data /shared/train --out /shared/runs/grpo --config configs/posttrain/paper.yaml --gpus-per-worker 1

Writes OUT/checkpoint-NNNNNNN/ (pretraining's format: evaluate.py --checkpoint OUT and RokenPlanner load it),
OUT/metrics.jsonl (rollout/*, losses/*, charts/*), TensorBoard files under OUT/tb and OUT/summary.json. The
same command again resumes at the saved iteration. --eval-episodes N evaluates the pretrained and the
post-trained model on the same N evaluation tasks at the end (OUT/eval-before, OUT/eval-after).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from common import (USER_ERRORS, add_common_args, explain_relative_out, fail, interrupted, make_runner,
                    named_overrides)

from roken.config import load_config
from roken.configtools import with_overrides
from roken.rl.config import check
from roken.rl.loop import PostTraining, summary_table
from roken.train.data import check_dataset


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True, help="pretrained checkpoint directory or run folder")
    ap.add_argument("--data", required=True, help="expert dataset the prompts come from (pipelines/generate.py)")
    ap.add_argument("--out", required=True, help="run folder (checkpoints, metrics); an absolute path for Ray")
    ap.add_argument("--iterations", type=int, help="rl.iterations")
    ap.add_argument("--prompts", type=int, dest="prompts_per_iteration", help="rl.prompts_per_iteration")
    ap.add_argument("--group-size", type=int, help="rl.group_size (G candidates per prompt)")
    ap.add_argument("--eval-episodes", type=int, help="before/after evaluation on this many tasks (rl.eval_episodes)")
    ap.add_argument("--eval-planners", help="rows of the before/after table (rl.eval_planners, default roken), e.g. "
                                            "roken,roken+guided,roken+guided+safe")
    ap.add_argument("--prompts-per-unit", type=int, default=4, help="prompts a rollout actor samples per request")
    ap.add_argument("--gpus-per-worker", type=float, default=None,
                    help="GPUs per rollout actor (default: 1 when the cluster has GPUs)")
    add_common_args(ap)
    return ap


def before_after(cfg, pretrained: str, out: Path, episodes: int, args) -> str:
    """Evaluate the pretrained and the post-trained model on the same tasks; returns the table."""
    from roken.eval.harness import evaluate

    rows = []
    for name, ckpt in (("before", pretrained), ("after", str(out))):
        c = with_overrides(cfg, {"eval.planner": cfg.rl.eval_planners, "eval.episodes": episodes,
                                 "eval.robots": [cfg.rl.eval_team_size], "plan.checkpoint": ckpt})
        m = evaluate(c, str(out / f"eval-{name}"), make_runner(args, gpus_per_worker=_gpus(args)), overwrite=True)
        rows.append((name, m))
    keys = ("full_success", "obstacle_collision", "inter_collision", "connectivity", "reach")
    lines = [f"{'model':8s} {'planner':20s} " + " ".join(f"{k:>18s}" for k in keys), "-" * (30 + 19 * len(keys))]
    lines += [f"{n:8s} {p:20s} " + " ".join(f"{pm[k]:18.3f}" for k in keys)
              for n, m in rows for p, pm in m.get("planners", {"roken": m}).items()]
    return "\n".join(lines)


def _gpus(args) -> float:
    return -1 if args.gpus_per_worker is None else args.gpus_per_worker


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    pt = None
    try:
        cfg = load_config(args.config, named_overrides(args, "rl", ("iterations", "prompts_per_iteration",
                                                                    "group_size", "eval_episodes", "eval_planners")))
        check(cfg.rl)
        explain_relative_out(args.out)
        if "://" in args.out:
            raise ValueError(f"--out {args.out}: post-training writes its run folder on a file system; give a local "
                             f"or shared (NFS) path")
        if args.prompts_per_unit < 1:
            raise ValueError(f"--prompts-per-unit {args.prompts_per_unit}: must be >= 1")
        out = Path(os.path.abspath(args.out))
        data = args.data if "://" in args.data else os.path.abspath(args.data)
        check_dataset(data)
        pt = PostTraining(cfg.rl, cfg.task, args.checkpoint, data, out, None, args.prompts_per_unit)
        pt.runner = make_runner(args, gpus_per_worker=_gpus(args))
        summary = pt.fit()
        print(summary_table(summary))
        if cfg.rl.eval_episodes > 0:
            print(before_after(cfg, pt.blob["path"], out, cfg.rl.eval_episodes, args))
    except USER_ERRORS as e:
        return fail(e)
    except KeyboardInterrupt:
        return interrupted("posttrain", os.path.abspath(args.out), getattr(pt, "iteration", None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
