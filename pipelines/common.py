"""What every pipeline shares: config flags, where to run (in-process, --local, a cluster), the runner.

Where a pipeline runs:
  --workers 0        in this process, no Ray (debugging: breakpoints and tracebacks work)
  --local            a private Ray cluster on this machine with its cores; replaces ray.init(local_mode=True),
                     which Ray removed in 2.55
  --address H:P      an existing cluster (cluster/start-head.sh); under `ray job submit` the cluster is found
                     from $RAY_ADDRESS without any flag
With none of these and no $RAY_ADDRESS, the pipeline runs in-process.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# Before anything imports Ray (torchrl does, on import): Ray reads the auth mode once. Token authentication
# stays on unless the user turned it off explicitly (RAY_AUTH_MODE=disabled).
os.environ.setdefault("RAY_AUTH_MODE", "token")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout (or a job's uploaded working dir) without installing

from roken.units import InProcessRunner, in_ray_job  # noqa: E402


# What a user's input can get wrong: ConfigError, StoreError, CheckpointError and MapError are ValueErrors, a
# cluster that cannot be reached is a ConnectionError (an OSError). Pipelines print these as one line, exit 2.
USER_ERRORS = (ValueError, OSError)


def fail(e: Exception) -> int:
    print(f"error: {e}", file=sys.stderr)
    return 2


def interrupted(stage: str, out: str, step: int | None) -> int:
    """Ctrl-C in a training pipeline: where it stopped, what is kept, how to go on; exit 130 like a shell."""
    from roken.train import checkpoint as ckpt

    try:
        found = ckpt.list_checkpoints(out)
        kept = f"checkpoint at step {ckpt.read_config(found[-1]).get('step')}" if found else "no checkpoint yet"
    except (OSError, ValueError):
        kept = "no checkpoint yet"
    at = f" at step {step}" if step is not None else ""
    print(f"[{stage}] interrupted{at}; {kept} in {out}; re-run the same command to resume", file=sys.stderr)
    return 130


def add_common_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--config", help="YAML config file (see configs/)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override any config field, e.g. --set expert.batch_size=32")
    ray_args = ap.add_argument_group("where to run")
    ray_args.add_argument("--workers", type=int,
                          help="Ray actors (default: one per CPU of the cluster); 0 = in-process, no Ray")
    ray_args.add_argument("--local", action="store_true",
                          help="start a private Ray cluster on this machine (laptop mode)")
    ray_args.add_argument("--num-cpus", type=int, help="CPUs of the --local cluster (default: all cores)")
    ray_args.add_argument("--address", help="join the Ray cluster at HOST:PORT (default: $RAY_ADDRESS)")


def named_overrides(args, section: str, names: tuple[str, ...]) -> list[str]:
    """--set flags, then the named flags that were given (they win), as `section.name=value` overrides."""
    return list(args.set) + [f"{section}.{n}={getattr(args, n)}" for n in names if getattr(args, n) is not None]


def wants_ray(args) -> bool:
    if args.workers is not None and args.workers < 0:
        raise ValueError(f"--workers {args.workers}: must be >= 0 (0 = in-process, no Ray)")
    if args.num_cpus is not None and args.num_cpus < 1:
        raise ValueError(f"--num-cpus {args.num_cpus}: must be >= 1 (CPUs of the --local cluster)")
    if args.workers == 0:
        if args.local or args.address:
            raise ValueError("--workers 0 runs in-process; drop --local / --address, or give --workers >= 1")
        return False
    return bool(args.local or args.address or os.environ.get("RAY_ADDRESS") or (args.workers or 0) > 0)


def make_runner(args, gpus_per_worker: float = 0):
    """The runner for these flags; connects to Ray only when it is needed (imports it only then too).
    gpus_per_worker -1: one GPU per actor when the cluster has GPUs (as many actors as GPUs), else none."""
    if not wants_ray(args):
        return InProcessRunner()
    from roken import ray_pool

    resources = ray_pool.connect(args.address, args.local, args.num_cpus, code_root=str(ROOT))
    cpus = int(resources.get("CPU", 1))
    gpus = int(resources.get("GPU", 0))
    if gpus_per_worker < 0:
        gpus_per_worker = 1 if gpus else 0
    if gpus_per_worker > 0:
        workers = args.workers or max(1, int(gpus / gpus_per_worker))
        return ray_pool.RayRunner(workers, num_gpus=gpus_per_worker)
    workers = args.workers or cpus
    if workers > cpus:
        print(f"note: {workers} workers on a cluster with {cpus} CPUs; the extra ones wait for free CPUs",
              file=sys.stderr)
    return ray_pool.RayRunner(workers)


def local_run_folder(out: str, what: str, file_hint: str = "") -> str:
    """--out of a training pipeline as an absolute local folder (Ray workers have another cwd), checked before
    anything is written: not a URI, not a file."""
    explain_relative_out(out)
    if "://" in out:
        raise ValueError(f"--out {out}: {what} writes its run folder on a file system; give a local or shared "
                         f"(NFS) path")
    path = os.path.abspath(out)
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"--out {out}: is a file; the {file_hint or 'run folder'} must be a folder")
    return path


def selfcost_states(cfg, need_states: bool = True) -> None:
    """The `selfcost` term's rollout folders, checked before anything is written and made absolute (Ray workers
    have another cwd). need_states=False: none given is fine (DAgger uses each round's rollouts)."""
    from roken.data.store import StoreError
    from roken.rl.selfcost import active, check

    check(cfg.selfcost, need_states)
    if not active(cfg.selfcost):
        return
    folders = [absolute(f.strip()) for f in cfg.selfcost.states.split(",") if f.strip()]
    for f in folders:
        if "://" not in f and not (Path(f) / "episodes").is_dir():
            raise StoreError(f"selfcost.states: {f} is not a folder of closed-loop rollouts (no episodes/ in it); "
                             f"make one with pipelines/evaluate.py --planner roken --maps train --out DIR")
    cfg.selfcost.states = ",".join(folders)


def absolute(location: str | None) -> str | None:
    """A local path made absolute (Ray workers have another cwd); URIs and None as they are."""
    return location if location is None or "://" in location else os.path.abspath(location)


def explain_relative_out(out: str) -> None:
    if "://" not in out and not os.path.isabs(out) and in_ray_job():
        print(f"note: --out {out} is relative; inside a Ray job it is {os.path.abspath(out)}, the job's "
              f"temporary working directory. Pass an absolute path or a URI (s3://, gs://) to keep it.",
              file=sys.stderr)
