"""Pretraining on Ray Train (real local clusters on 127.0.0.1): DDP with 2 CPU workers writes checkpoints and
metrics, a worker killed mid-run is replaced and the group restarts from the last checkpoint (1 Ray Train
worker against the in-process loop runs on the shared head in test_ray_cluster.py)."""
import json
import os
import subprocess
import sys
from pathlib import Path


import pytest

from roken.train import checkpoint as ckpt

pytestmark = pytest.mark.slow  # a real local Ray cluster

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--preset", "tiny", "--batch-size", "8", "--set", "train.loader_workers=0", "--set", "train.log_every=1",
        "--set", "train.val_fraction=0.34", "--set", "train.val_prompts=4", "--set", "train.eval_every=3",
        "--set", "train.checkpoint_every=3", "--set", "train.warmup_steps=2", "--set", "train.closed_loop_every=0"]


def pretrain(data, out, steps, *extra, env=None, ray_tmp=None):
    e = dict(os.environ, RAY_TMPDIR=ray_tmp or "/tmp", **(env or {}))
    return subprocess.run([sys.executable, str(ROOT / "pipelines" / "pretrain.py"), "--data", data, "--out", str(out),
                           "--steps", str(steps), *TINY, *extra], capture_output=True, text=True, timeout=600, env=e)


def rows(out):
    return [json.loads(x) for x in (Path(out) / "metrics.jsonl").read_text().splitlines()]


def test_two_workers_survive_a_killed_worker_and_resume(expert_dataset, tmp_path, ray_tmp):
    out = tmp_path / "run"
    marker = tmp_path / "killed"
    r = pretrain(expert_dataset, out, 6, "--local", "--num-cpus", "2", "--workers", "2", "--max-failures", "2",
                 env={"ROKEN_KILL_WORKER": f"1:6:{marker}"}, ray_tmp=ray_tmp)
    assert r.returncode == 0, r.stderr[-3000:]
    log = r.stdout + r.stderr  # worker lines reach the driver's console through Ray
    assert marker.exists(), "rank 1 was killed at step 6"
    assert "global batch 8 = 4 x 2 worker(s)" in log
    assert "resuming at step 3" in log, "the restarted group went on from the step-3 checkpoint"
    assert [c.name for c in ckpt.list_checkpoints(out)] == ["checkpoint-0000003", "checkpoint-0000006"]
    assert [x["step"] for x in rows(out)] == [1, 2, 3, 4, 5, 6]
    cfg = ckpt.read_config(ckpt.find(out))
    assert cfg["step"] == 6 and cfg["world_size"] == 2
    assert "3 -> 6" in r.stdout and "checkpoint-0000006" in r.stdout
    ckpt.load(out)  # the planner's loader reads what Ray persisted
    # (running the same command again resumes: the in-process pipeline test checks it on the same run folder
    # layout, and the restart above went through the same resume path)
