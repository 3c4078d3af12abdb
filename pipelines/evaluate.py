"""Evaluate a planner on generated or external maps and print the paper-style table.

    python pipelines/evaluate.py --planner laplacian --robots 2,4,8 --episodes 200 --maps eval --out runs/eval
    python pipelines/evaluate.py --robots 2,4,6,8,10 --episodes 1000 --out runs/eval --local
    python pipelines/evaluate.py --maps ../shared/data/movingai --robots 4 --episodes 13 --out runs/movingai

Episodes are cut into units (eval.unit_episodes per team size) and fanned out over Ray actors with --local,
--address or under `ray job submit`; --workers 0 runs the same units in-process (no Ray) and gives the same
episodes. Any config field can be set with --config FILE.yaml and --set dotted.key=value.
"""
from __future__ import annotations

import argparse
import sys

from common import add_common_args, explain_relative_out, make_runner, named_overrides

from roken.config import ConfigError, load_config
from roken.data.store import StoreError
from roken.eval.harness import check, evaluate


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--planner", help="planner name (laplacian)")
    ap.add_argument("--robots", help="team size or list, e.g. 4 or 2,4,8")
    ap.add_argument("--episodes", type=int, help="episodes per team size")
    ap.add_argument("--maps", help="train, eval, or a folder / glob / file of .map, .png, .npy maps")
    ap.add_argument("--num-maps", type=int, help="use at most this many maps")
    ap.add_argument("--seed", type=int, help="task seed")
    ap.add_argument("--out", required=True, help="output folder or URI (maps/, episodes/, metrics.json)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace an evaluation made with a different config in --out")
    add_common_args(ap)
    return ap


def overrides(args) -> list[str]:
    return named_overrides(args, "eval", ("planner", "robots", "episodes", "maps", "num_maps", "seed"))


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        cfg = load_config(args.config, overrides(args))
        explain_relative_out(args.out)
        check(cfg.eval)  # before a Ray cluster starts or anything is written
        metrics = evaluate(cfg, args.out, make_runner(args), overwrite=args.overwrite)
    except (ConfigError, StoreError, ValueError, OSError, ConnectionError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 1 if metrics["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
