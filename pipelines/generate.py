"""Generate an expert dataset: the Laplacian expert over map units, into Parquet shards.

    python pipelines/generate.py --maps train --num-maps 200 --episodes-per-map 10 --out data/train --local
    ray job submit --runtime-env cluster/runtime_env.yaml --working-dir . -- \\
        python pipelines/generate.py --maps train --num-maps 5000 --out s3://bucket/roken/train

Writes OUT/maps/unit-*.parquet, OUT/episodes/unit-*.parquet and OUT/manifest.json. Re-running the same
command finishes an interrupted run (finished shards are kept and skipped). The team-size mix, maps per unit
and the rest are config fields (section `dataset`), settable with --config / --set.
"""
from __future__ import annotations

import argparse
import sys

from common import USER_ERRORS, add_common_args, explain_relative_out, fail, make_runner, named_overrides

from roken.config import load_config
from roken.data.build import Interrupted, build_dataset, parse_shard
from roken.data.generation import check


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--maps", help="train, val, eval, or a folder / glob / file of .map, .png, .npy maps")
    ap.add_argument("--num-maps", type=int, help="use at most this many maps")
    ap.add_argument("--episodes-per-map", type=int, help="episodes per map (default 10)")
    ap.add_argument("--seed", type=int, help="task seed")
    ap.add_argument("--shard", metavar="K/N", help="run only units u with u %% N == K (N processes, no Ray, one "
                                                   "dataset: a Slurm array, a GPU box)")
    ap.add_argument("--out", required=True, help="output folder or URI (s3://..., gs://..., file://...)")
    add_common_args(ap)
    return ap


def overrides(args) -> list[str]:
    return named_overrides(args, "dataset", ("maps", "num_maps", "episodes_per_map", "seed"))


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        cfg = load_config(args.config, overrides(args))
        shard = parse_shard(args.shard)
        check(cfg.dataset, cfg.expert)  # before a Ray cluster starts or anything is written
        explain_relative_out(args.out)
        runner = make_runner(args)
        manifest = build_dataset(cfg, args.out, runner, shard)
    except Interrupted as e:
        print(f"[generate] {e}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("[generate] interrupted while starting; re-run the same command", file=sys.stderr)
        return 130
    except USER_ERRORS as e:
        return fail(e)
    if shard is not None:
        return 0 if not manifest["failures"] else 1
    return 0 if manifest["status"] == "complete" else 1


if __name__ == "__main__":
    sys.exit(main())
