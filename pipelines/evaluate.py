"""Evaluate a planner on generated or external maps and print the paper-style table.

    python pipelines/evaluate.py --planner laplacian --robots 2,4,8 --episodes 200 --maps eval --out runs/eval
    python pipelines/evaluate.py --maps ../shared/data/movingai --robots 4 --episodes 13 --out runs/movingai

--workers 0 (the default) runs in-process without Ray: the debug mode that replaces Ray's removed
`local_mode`. Any config field can be set with --config FILE.yaml and --set dotted.key=value.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

from roken.config import ConfigError, load_config  # noqa: E402
from roken.data.store import StoreError  # noqa: E402
from roken.eval.harness import evaluate  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", help="YAML config file")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    ap.add_argument("--planner", help="planner name (laplacian)")
    ap.add_argument("--robots", help="team size or list, e.g. 4 or 2,4,8")
    ap.add_argument("--episodes", type=int, help="episodes per team size")
    ap.add_argument("--maps", help="train, eval, or a folder / glob / file of .map, .png, .npy maps")
    ap.add_argument("--num-maps", type=int, help="use at most this many maps")
    ap.add_argument("--seed", type=int, help="task seed")
    ap.add_argument("--workers", type=int, help="0 = in-process (no Ray)")
    ap.add_argument("--out", required=True, help="output folder (maps/, episodes/, metrics.json)")
    args = ap.parse_args(argv)
    overrides = list(args.set)
    for key, val in (("planner", args.planner), ("robots", args.robots), ("episodes", args.episodes),
                     ("maps", args.maps), ("num_maps", args.num_maps), ("seed", args.seed),
                     ("workers", args.workers)):
        if val is not None:
            overrides.append(f"eval.{key}={val}")
    try:
        cfg = load_config(args.config, overrides)
        evaluate(cfg, args.out)
    except (ConfigError, StoreError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
