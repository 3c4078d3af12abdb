"""The paper's sweeps for a checkpoint: scalability, replanning frequency, sensing range (roken.eval.sweeps).

    python pipelines/sweep.py --checkpoint models/roken-small-mixed --episodes 200 --out runs/sweeps --local
    python pipelines/sweep.py --checkpoint RUN_DIR --sweeps replanning --episodes 50 --out runs/sw --workers 0
    # the deployable row beside the paper's planner, on the same tasks
    python pipelines/sweep.py --checkpoint models/roken-cpu-four --planners roken,roken+guided+geodesic \
        --candidates 8 --episodes 50 --out runs/sweeps --local

Writes OUT/<sweep>.json, .md and .png, and one evaluation folder per setting (re-running resumes).
"""
from __future__ import annotations

import argparse
import sys

from common import USER_ERRORS, add_common_args, explain_relative_out, fail, make_runner

from roken.config import load_config
from roken.eval.harness import check, load_model
from roken.eval.sweeps import SWEEPS, check_rows, run_sweep


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True, help="checkpoint directory or run folder")
    ap.add_argument("--sweeps", default=",".join(SWEEPS), help=f"comma list of {', '.join(SWEEPS)}")
    ap.add_argument("--episodes", type=int, default=200, help="episodes per setting")
    ap.add_argument("--maps", default="eval", help="eval, val, train, or a folder of map files")
    ap.add_argument("--planners", default="roken",
                    help="Roken rows of every setting, e.g. roken,roken+guided+geodesic (default: roken)")
    ap.add_argument("--candidates", type=int, help="G candidates of the selection rows (plan.candidates)")
    ap.add_argument("--out", required=True)
    add_common_args(ap)
    args = ap.parse_args(argv)
    try:
        extra = [f"plan.candidates={args.candidates}"] if args.candidates is not None else []
        cfg = load_config(args.config, list(args.set) + extra + [
            f"plan.checkpoint={args.checkpoint}", "eval.planner=roken", f"eval.episodes={args.episodes}",
            f"eval.maps={args.maps}"])
        planners = tuple(p.strip() for p in args.planners.split(",") if p.strip())
        explain_relative_out(args.out)
        check(cfg.eval)
        blob, _ = load_model(cfg)
        names = [s.strip() for s in args.sweeps.split(",") if s.strip()]
        bad = [s for s in names if s not in SWEEPS]
        if bad:
            raise ValueError(f"--sweeps: unknown {', '.join(bad)}; choose from {', '.join(SWEEPS)}")
        check_rows(planners)
        runner = make_runner(args, gpus_per_worker=-1 if cfg.plan.device != "cpu" else 0)
        for name in names:
            run_sweep(cfg, name, args.out, blob["config"]["samples"]["max_robots"], runner, planners)
            print(open(f"{args.out}/{name}.md").read())
    except USER_ERRORS as e:
        return fail(e)
    return 0


if __name__ == "__main__":
    sys.exit(main())
