"""DAgger: roll a Roken model out in closed loop, let the Laplacian expert continue from the states it visited,
train on the expert dataset mixed with those continuations; repeat (roken/dagger).

    python pipelines/dagger.py --checkpoint runs/cpu-k1 --data data/train4 --val-data data/val4 \\
        --out runs/dagger --config configs/dagger/cpu.yaml --workers 0
    python pipelines/dagger.py --checkpoint runs/cpu-k1 --data data/train4 --out $PWD/runs/dagger \\
        --config configs/dagger/cpu.yaml --local --workers 2
    ray job submit --working-dir . -- python pipelines/dagger.py --checkpoint /shared/runs/mixed \\
        --data /shared/train --out /shared/runs/dagger --rounds 8 --episodes 512

Rollouts run on Ray actors (or in-process with --workers 0), training in-process or on Ray Train workers.
Writes OUT/round-rr/{rollouts,data,train,summary.json}, OUT/summary.json and a per-round table; the same
command resumes at the unfinished stage of the unfinished round, and a finished run prints its table.
--config takes a pretraining config plus a `dagger:` section; the model, diffusion, samples and loss sections
are the checkpoint's.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from common import (ROOT, USER_ERRORS, absolute, add_common_args, fail, local_run_folder, make_runner,
                    named_overrides, selfcost_states, wants_ray)

from roken.config import load_config
from roken.configtools import to_dict
from roken.dagger import run_dagger, summary_table
from roken.train import checkpoint as ckpt
from roken.train.data import check_dataset
from roken.train.loop import Pretraining, PretrainSpec


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True, help="the model to start from: a checkpoint or a run folder")
    ap.add_argument("--data", required=True, help="the expert dataset (pipelines/generate.py --maps train)")
    ap.add_argument("--out", required=True, help="DAgger run folder; an absolute path for Ray")
    ap.add_argument("--val-data", help="held-out dataset for the open-loop diagnostics (generate.py --maps val)")
    ap.add_argument("--rounds", type=int, help="dagger.rounds")
    ap.add_argument("--episodes", type=int, help="closed-loop rollouts per round (dagger.episodes)")
    ap.add_argument("--steps-per-round", type=int, help="training steps per round (dagger.steps_per_round)")
    ap.add_argument("--share", type=float, help="share of samples from relabelled episodes (dagger.share)")
    ap.add_argument("--cpus-per-worker", type=float, default=1.0, help="CPUs per Ray Train worker")
    add_common_args(ap)
    return ap


def from_checkpoint(cfg, checkpoint: str):
    """A round continues the checkpoint's model: its model, diffusion, samples and loss sections replace the
    config's (--config and --set give the train, dagger and plan sections)."""
    from roken.configtools import from_dict

    c = ckpt.read_config(ckpt.find(checkpoint))
    for sec in ("model", "diffusion", "samples", "loss"):
        if sec in c:
            setattr(cfg, sec, from_dict(type(getattr(cfg, sec)), c[sec], sec + "."))
    return cfg


def trainer(args):
    """One round's training: in-process, or Ray Train with --workers N (the loop is the same)."""
    def in_process(cfg, datasets, shares, out, val_data, init):
        return Pretraining(PretrainSpec.of(cfg), datasets, out, val_data, data_shares=shares, init=init).fit()

    def on_ray(cfg, datasets, shares, out, val_data, init):
        from roken import ray_train
        from roken.data.store import read_json

        ray_train.fit(ray_train.pretrain_worker, {"config": to_dict(cfg), "data": datasets, "shares": shares,
                                                  "out": out, "val_data": val_data, "init": init, "root": str(ROOT)},
                      out, args.workers or 1, args.cpus_per_worker, 0.0, 0, cfg.train.keep_checkpoints)
        return read_json(Path(out) / "summary.json")
    return on_ray if wants_ray(args) else in_process


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    out = args.out
    try:
        out = local_run_folder(args.out, "DAgger", "DAgger run folder")
        sets = named_overrides(args, "dagger", ("rounds", "episodes", "steps_per_round", "share"))
        cfg = from_checkpoint(load_config(args.config, sets), args.checkpoint)
        args.data, args.val_data = absolute(args.data), absolute(args.val_data)
        selfcost_states(cfg, need_states=False)  # its own states, if given (else each round's rollouts)
        check_dataset(args.data, "--data")
        if args.val_data:
            check_dataset(args.val_data, "--val-data")
        if wants_ray(args):  # bad --workers / --num-cpus fail here, before anything is written
            from roken import ray_pool

            # the dashboard's state API is what Ray Train's placement-group cleaner polls (pretrain.py does this too)
            ray_pool.connect(args.address, args.local, args.num_cpus, code_root=str(ROOT), dashboard=True)
        result = run_dagger(cfg, args.checkpoint, args.data, out, lambda: make_runner(args), trainer(args),
                            args.val_data, log=lambda m: print(m, file=sys.stderr))
    except USER_ERRORS as e:
        return fail(e)
    except KeyboardInterrupt:
        done = sorted(p.parent.name for p in Path(out).glob("round-*/summary.json"))
        print(f"[dagger] interrupted; {len(done)} finished round(s) in {out} ({', '.join(done) or 'none'}) and the "
              f"finished stages of the next are kept; re-run the same command to resume", file=sys.stderr)
        return 130
    print(summary_table(result))
    print(f"model: {result['checkpoint']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
