"""The thin Ray Train layer of pretraining (like `ray_pool` for actors): a TorchTrainer around the same loop.

Ray Train v2 (the default in Ray 2.60) runs `train_loop_per_worker` in a group of workers with DDP set up
(gloo on CPU, nccl on GPU). Checkpoints are directories reported through `ray.train.report`, persisted by Ray
under storage_path/name/checkpoint-NNNNNNN - the run folder's own layout, so the in-process loop, the planner
and a resumed run read them alike. A second `fit()` with the same storage_path and name resumes from the
latest checkpoint, and `FailureConfig(max_failures)` restarts a group that lost a worker from it.
"""
from __future__ import annotations

import os
import shutil
import signal
import tempfile
from pathlib import Path

import ray.train
import ray.train.torch
from ray.train import CheckpointConfig, FailureConfig, RunConfig, ScalingConfig
from ray.train.torch import TorchTrainer

from .train import checkpoint as ckpt


class RayTrainBackend:
    """What differs for `roken.train.loop.Pretraining` inside a Ray Train worker."""

    def __init__(self, loss_cfg, run_dir: str):
        self.run_dir = Path(run_dir)
        ctx = ray.train.get_context()
        self.rank, self.world = ctx.get_world_rank(), ctx.get_world_size()
        self.device = ray.train.torch.get_device()
        # DDP fails on parameters that get no gradient: the auxiliary heads when their loss weight is 0.
        self.find_unused = loss_cfg.wp == 0 or loss_cfg.occ == 0
        self._restored: str | None = None

    def prepare(self, model):
        # Wraps in DDP only when world size > 1 (and moves to this worker's device).
        return ray.train.torch.prepare_model(model, parallel_strategy_kwargs={
            "find_unused_parameters": self.find_unused})

    def resume_from(self) -> Path | None:
        """The newest checkpoint: Ray's (get_checkpoint) or, newer, one Ray persisted into the run folder that
        its controller had not registered yet when the group failed (seen with checkpoints seconds apart)."""
        c = ray.train.get_checkpoint()
        if c is not None:
            self._restored = c.to_directory()  # a local copy (downloaded when the storage is remote)
        candidates = [Path(self._restored)] if self._restored else []
        candidates += ckpt.list_checkpoints(self.run_dir) if self.run_dir.is_dir() else []
        steps = {p: ckpt.read_config(p).get("step", -1) for p in candidates if (p / ckpt.STATE).is_file()}
        return max(steps, key=steps.get) if steps else None

    def report(self, step: int, metrics: dict, write=None, keep: int = 3) -> None:
        _injected_failure(self.rank, step)
        name = ckpt.checkpoint_name(step)
        if write is None:  # the other ranks take part in the report without a checkpoint
            ray.train.report(metrics, checkpoint=None, checkpoint_dir_name=name)
            return
        tmp = tempfile.mkdtemp(prefix="roken-ckpt-")
        try:
            write(Path(tmp))
            ray.train.report(metrics, checkpoint=ray.train.Checkpoint.from_directory(tmp), checkpoint_dir_name=name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def pretrain_worker(config: dict) -> None:
    """Ray Train's per-worker function: the in-process loop with the Ray backend. `config` holds the root
    config as a dict, the data (one folder or several with `shares`), the run folder and an optional `init`."""
    import sys

    sys.path.insert(0, config["root"])
    from .config import Config
    from .configtools import from_dict
    from .train.loop import Pretraining, PretrainSpec

    cfg = from_dict(Config, config["config"])
    Pretraining(PretrainSpec.of(cfg), config["data"], config["out"], config["val_data"],
                backend=RayTrainBackend(cfg.loss, config["out"]), data_shares=config.get("shares"),
                init=config.get("init")).fit()


def _injected_failure(rank: int, step: int) -> None:
    """Fault injection for the recovery test: ROKEN_KILL_WORKER="RANK:STEP:MARKER" makes that worker SIGKILL
    itself at that step's report, once (the marker file records it), as an OOM kill or a lost node would."""
    spec = os.environ.get("ROKEN_KILL_WORKER")
    if not spec:
        return
    r, s, marker = spec.split(":", 2)
    if int(r) == rank and int(s) == step and not os.path.exists(marker):
        Path(marker).write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)


def fit(loop, loop_config: dict, out: str, workers: int, cpus_per_worker: float, gpus_per_worker: float,
        max_failures: int, keep: int):
    out = os.path.abspath(out)
    scaling = ScalingConfig(num_workers=workers, use_gpu=gpus_per_worker > 0,
                            resources_per_worker={"CPU": cpus_per_worker} | (
                                {"GPU": gpus_per_worker} if gpus_per_worker > 0 else {}))
    run = RunConfig(name=os.path.basename(out), storage_path=os.path.dirname(out),
                    failure_config=FailureConfig(max_failures=max_failures),
                    checkpoint_config=CheckpointConfig(num_to_keep=keep))
    return TorchTrainer(loop, train_loop_config=loop_config, scaling_config=scaling, run_config=run).fit()
