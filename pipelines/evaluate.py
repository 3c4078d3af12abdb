"""Evaluate a planner on generated or external maps and print the paper-style table.

    python pipelines/evaluate.py --planner laplacian --robots 2,4,8 --episodes 200 --maps eval --out runs/eval
    python pipelines/evaluate.py --robots 2,4,6,8,10 --episodes 1000 --out runs/eval --local
    python pipelines/evaluate.py --maps ../shared/data/movingai --robots 4 --episodes 13 --out runs/movingai
    python pipelines/evaluate.py --planner laplacian,roken,roken+safe --checkpoint models/roken-small-mixed \
        --robots 4 --episodes 200 --out runs/eval-roken --local
    python pipelines/evaluate.py --planner roken --checkpoint RUN_DIR --robots 10 --cluster-size 4 --out runs/n10

Episodes are cut into units (eval.unit_episodes per team size) and fanned out over Ray actors with --local,
--address or under `ray job submit`; --workers 0 runs the same units in-process (no Ray) and gives the same
episodes. Any config field can be set with --config FILE.yaml and --set dotted.key=value.
"""
from __future__ import annotations

import argparse
import sys

from common import USER_ERRORS, add_common_args, explain_relative_out, fail, make_runner, named_overrides

from roken.config import load_config
from roken.eval.harness import check, evaluate, load_model, uses_roken


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--planner", help="planner or list: laplacian, sgg, gnn, roken, roken+safe, roken+geodesic, "
                                      "roken+guided, roken+guided+safe (e.g. laplacian,sgg,gnn,roken: one table, "
                                      "the same tasks)")
    ap.add_argument("--robots", help="team size or list, e.g. 4 or 2,4,8")
    ap.add_argument("--episodes", type=int, help="episodes per team size")
    ap.add_argument("--maps", help="train, val, eval, or a folder / glob / file of .map, .png, .npy maps")
    ap.add_argument("--num-maps", type=int, help="use at most this many maps")
    ap.add_argument("--seed", type=int, help="task seed")
    ap.add_argument("--out", required=True, help="output folder or URI (maps/, episodes/, metrics.json)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace an evaluation made with a different config in --out")
    rk = ap.add_argument_group("Roken planner (plan.* in the config)")
    rk.add_argument("--checkpoint", help="checkpoint directory or run folder (e.g. models/roken-small-mixed)")
    rk.add_argument("--which", choices=["latest", "best"], help="a run folder's latest or best checkpoint")
    rk.add_argument("--replan-every", type=int, help="chunk moves executed per re-plan (default 2)")
    rk.add_argument("--cluster-size", type=int, help="clustered rollout with clusters of at most this many "
                                                      "robots (0 = direct, default)")
    rk.add_argument("--sensing-range", type=float, help="metres the team sees around each robot (0 = whole map)")
    rk.add_argument("--accumulate", action="store_const", const=True, help="keep what was seen at earlier re-plans")
    rk.add_argument("--candidates", type=int, help="candidates per re-plan for roken+safe / roken+geodesic")
    rk.add_argument("--select", choices=["none", "safe", "geodesic"], help="selection for the `roken` row")
    rk.add_argument("--guide-scale", type=float, help="roken+guided: scale of the guidance descent (default 1)")
    rk.add_argument("--guide-steps", type=int,
                    help="roken+guided: the last DDIM steps that are guided (default plan.guide_steps)")
    rk.add_argument("--subgoal", type=float, help="metres of free-space path the leader's sub-goal lies ahead on the "
                                                  "known map (0 = the task's goal, default; roken/plan/subgoal.py)")
    rk.add_argument("--sampler", choices=["ddim", "ddpm"])
    rk.add_argument("--steps", type=int, help="DDIM steps (default 10)")
    rk.add_argument("--device", help="auto (cuda where available, default), cpu or cuda")
    rk.add_argument("--dtype", choices=["fp32", "bf16"], help="bf16 = autocast (GPU)")
    rk.add_argument("--gpus-per-worker", type=float, default=None,
                    help="GPUs per Ray actor (default: 1 when the cluster has GPUs and --device is not cpu)")
    add_common_args(ap)
    return ap


PLAN_FLAGS = ("checkpoint", "which", "replan_every", "cluster_size", "sensing_range", "accumulate", "candidates",
              "select", "sampler", "steps", "device", "dtype", "guide_scale", "guide_steps", "subgoal")


def overrides(args) -> list[str]:
    return (named_overrides(args, "eval", ("planner", "robots", "episodes", "maps", "num_maps", "seed"))
            + named_overrides(argparse.Namespace(set=[], **{k: getattr(args, k) for k in PLAN_FLAGS}), "plan",
                              PLAN_FLAGS))


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        cfg = load_config(args.config, overrides(args))
        explain_relative_out(args.out)
        check(cfg.eval)  # before a Ray cluster starts or anything is written
        load_model(cfg)  # a missing or unusable checkpoint, or a team too large for it, is said up front
        gpus = args.gpus_per_worker
        if gpus is None:
            gpus = -1 if uses_roken(cfg.eval) and cfg.plan.device != "cpu" else 0  # -1: 1 if the cluster has GPUs
        metrics = evaluate(cfg, args.out, make_runner(args, gpus_per_worker=gpus), overwrite=args.overwrite)
    except USER_ERRORS as e:
        return fail(e)
    return 1 if metrics["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
