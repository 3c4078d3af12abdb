"""GRPO post-training: advantages, the privileged reward, the first-minibatch ratio, the hard-prompt sampler, an
end-to-end run that resumes, and rollout actors on Ray with one killed mid-iteration."""
import json
import os
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from roken.data.samples import SampleConfig
from roken.model.diffusion import DiffusionConfig
from roken.model.dit import RokenDiT, preset
from roken.plan import RokenPlanner
from roken.rl.config import RLConfig
from roken.rl.grpo import Learner, group_advantages
from roken.rl.hard import HardPrompts
from roken.rl.loop import PostTraining
from roken.rl.prompts import condition
from roken.rl.rewards import privileged, score
from roken.rl.rollout import RolloutWorker
from roken.train import checkpoint as ckpt
from roken.units import InProcessRunner, Shared
from roken.world.grid import GridMap
from roken.world.tasks import TaskConfig

ROOT = Path(__file__).resolve().parents[1]
SMALL = {"group_size": 4, "prompts_per_iteration": 4, "train_transitions": 3, "minibatch_prompts": 2,
         "min_future": 32, "lr": 1e-3, "hard_prompt_prob": 0.5, "checkpoint_every": 1, "hard_cost": 1000.0}


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    """A random tiny model with 20 diffusion steps as a checkpoint directory."""
    torch.manual_seed(0)
    model = RokenDiT(preset("tiny"))
    for p in model.final.parameters():  # AdaLN-Zero starts at eps = 0; make the output non-trivial
        torch.nn.init.normal_(p, std=0.2)
    d = tmp_path_factory.mktemp("tiny") / "ckpt"
    cfg = {"model": asdict(preset("tiny")), "diffusion": asdict(DiffusionConfig(num_steps=20)),
           "samples": asdict(SampleConfig()), "loss": {}, "step": 0}
    ckpt.write(d, model.state_dict(), cfg)
    return str(d)


def test_group_advantages_known_rewards_and_flat_group():
    r = np.array([[1.0, 2.0, 3.0, 4.0], [5.0, 5.0, 5.0, 5.0]])
    a = group_advantages(r, min_std=1e-3, eps=0.0)
    expected = (r[0] - 2.5) / np.std(r[0])
    assert np.allclose(a[0], expected) and abs(a[0].mean()) < 1e-6
    assert np.array_equal(a[1], np.zeros(4)), "a flat group ranks nothing"


def test_reward_ranks_hand_made_chunks():
    occ = np.zeros((140, 140), np.uint8)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = 1
    occ[80:90, 20:45] = 1  # a block above the team
    gm = GridMap("hand", occ)
    tc, rc = TaskConfig(), RLConfig()
    start = np.array([[30.0, 70.0], [34.0, 70.0], [30.0, 74.0]])
    goal = np.array([110.0, 70.0])
    steps = np.arange(1, 17)[:, None]

    def move(v):  # (n, 2) metres per chunk move -> (n, 16, 2) planned points
        return start[:, None] + steps[None] * np.asarray(v, float)[:, None]

    fast = move([[1.5, 0], [1.5, 0], [1.5, 0]])
    slow = move([[0.5, 0], [0.5, 0], [0.5, 0]])
    obstacle = move([[1.5, 0], [1.5, 0], [0, 1.0]])  # robot 2 drives into the block
    disconnect = move([[1.5, 0], [-1.5, 0], [1.5, 0]])  # robot 1 leaves the team
    inter = fast.copy()
    inter[1] = start[0] + (steps * np.array([1.5, 0.0]))  # robot 1 drives through robot 0
    plans = np.stack([fast, slow, obstacle, disconnect, inter])
    info = privileged(gm, start, 0, goal, 32.0)
    r, terms = score(plans, start, info, tc, rc, interval=4)
    assert list(terms["hard"]) == [False, False, True, True, True]
    assert terms["obs"][2] and terms["conn"][3] and terms["inter"][4]
    assert r[0] > r[1] > max(r[2:]), r


def test_first_minibatch_after_a_sync_has_ratio_one_and_zero_kl(tiny_ckpt, expert_dataset):
    rc = RLConfig(**SMALL)
    tc = TaskConfig()
    blob = RokenPlanner.pack(tiny_ckpt)
    worker = RolloutWorker(blob, expert_dataset, tc, rc)
    pl = RokenPlanner.unpack(blob)
    learner = Learner(pl.model, RokenPlanner.unpack(blob).model, pl.schedule, rc, torch.device("cpu"))
    worker.set_weights(Shared(0, value=pl.model.state_dict()))
    prompt = (0, 5)
    g = worker.group(prompt)
    assert g.x_k.shape[:2] == (3, 4) and g.steps == sorted(g.steps, reverse=True) and 0 not in g.steps
    cond = condition(worker.bank, prompt, pl.cfg)
    adv = np.array([1.0, -1.0, 0.5, -0.5], np.float32)
    _, st = learner.group_loss(g, cond, adv)
    assert st["ratio_dev"] == 0.0 and st["kl"] == 0.0 and st["approx_kl"] == 0.0
    with torch.no_grad():  # the learner moved on but the worker still has version 0: the check sees it
        for p in pl.model.parameters():
            p.add_(1e-3 * torch.randn_like(p))
    _, st = learner.group_loss(g, cond, adv)
    assert st["ratio_dev"] > 1e-4 and st["kl"] > 0


def test_priority_sampler_draws_hard_prompts_more_often():
    store = HardPrompts(64, seed=0)
    store.add([(0, 0), (1, 0), (2, 0), (3, 0)], [0.9, 0.1, 0.1, 0.1])
    drawn = store.draw(4000)
    share = sum(p == (0, 0) for p in drawn) / len(drawn)
    assert abs(share - 0.9 / 1.2) < 0.03, share
    again = HardPrompts(64, seed=0)
    again.add([(0, 0), (1, 0), (2, 0), (3, 0)], [0.9, 0.1, 0.1, 0.1])
    assert again.draw(4000) == drawn  # a fixed seed draws the same


def _weights(run):
    from safetensors.torch import load_file
    return load_file(str(ckpt.find(run) / ckpt.WEIGHTS))


def test_posttraining_updates_the_weights_writes_a_loadable_checkpoint_and_resumes(tiny_ckpt, expert_dataset,
                                                                                   tmp_path):
    tc = TaskConfig()
    out = tmp_path / "grpo"
    PostTraining(RLConfig(**SMALL | {"iterations": 2}), tc, tiny_ckpt, expert_dataset, out, InProcessRunner()).fit()
    before = _weights(tiny_ckpt)
    after = _weights(out)
    assert any(not torch.equal(before[k], after[k]) for k in before), "GRPO changed the weights"
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2]
    for key in ("rollout/reward_mean", "rollout/zero_std_frac", "rollout/constraint_ok_frac", "losses/policy",
                "losses/kl_ref", "losses/approx_kl", "losses/clipfrac", "charts/weight_version_lag"):
        assert key in rows[-1]
    assert rows[0]["losses/ratio_dev_first"] < 1e-5 and rows[-1]["charts/weight_version_lag"] == 0
    planner = RokenPlanner.load(out)  # the planner loads a post-trained run folder like a pretrained one
    plan = planner.plan(np.zeros((140, 140), np.uint8), np.array([[50.0, 50.0], [54.0, 50.0]]), 0, (90, 90))
    assert plan.shape == (2, 16, 2)
    # resume: a third iteration on top of the saved two equals a straight three-iteration run
    PostTraining(RLConfig(**SMALL | {"iterations": 3}), tc, tiny_ckpt, expert_dataset, out, InProcessRunner()).fit()
    straight = tmp_path / "straight"
    PostTraining(RLConfig(**SMALL | {"iterations": 3}), tc, tiny_ckpt, expert_dataset, straight,
                 InProcessRunner()).fit()
    a, b = _weights(out), _weights(straight)
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="other settings"):
        PostTraining(RLConfig(**SMALL | {"iterations": 4, "lr": 1e-4}), tc, tiny_ckpt, expert_dataset, out,
                     InProcessRunner()).fit()


def test_overlapped_rollout_learns_on_groups_one_version_behind(tiny_ckpt, expert_dataset, tmp_path):
    out = tmp_path / "overlap"
    PostTraining(RLConfig(**SMALL | {"iterations": 3, "overlap": True}), TaskConfig(), tiny_ckpt, expert_dataset, out,
                 InProcessRunner()).fit()
    rows = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["charts/weight_version_lag"] for r in rows] == [0, 1, 1]
    assert [r["rollout/groups"] for r in rows] == [4, 4, 4] and rows[-1]["rollout/stale_groups"] == 0
    assert rows[1]["losses/ratio_dev_first"] > 0  # sampled by the weights before the last update
    assert any(not torch.equal(a, b) for a, b in zip(_weights(out).values(), _weights(tiny_ckpt).values()))


@pytest.mark.slow
def test_two_rollout_actors_with_one_killed_lose_no_group(tiny_ckpt, expert_dataset, tmp_path, ray_tmp):
    """A rollout actor killed mid-iteration is replaced and its prompts re-queued: every group arrives exactly
    once, so the weights equal the in-process run's."""
    args = ["--checkpoint", tiny_ckpt, "--data", expert_dataset, "--iterations", "1"] + \
        [a for k, v in SMALL.items() for a in ("--set", f"rl.{k}={v}")] + ["--prompts-per-unit", "1"]
    cmd = [sys.executable, str(ROOT / "pipelines" / "posttrain.py")]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the Ray actors and the driver below run: the same floating-point sums
    try:
        PostTraining(RLConfig(**SMALL | {"iterations": 1}), TaskConfig(), tiny_ckpt, expert_dataset, tmp_path / "ref",
                     InProcessRunner(), prompts_per_unit=1).fit()
    finally:
        torch.set_num_threads(threads)
    marker = tmp_path / "killed"
    env = os.environ | {"OMP_NUM_THREADS": "1", "RAY_TMPDIR": ray_tmp, "ROKEN_KILL_ROLLOUT": str(marker)}
    r = subprocess.run(cmd + args + ["--out", str(tmp_path / "ray"), "--local", "--workers", "2", "--num-cpus", "2"],
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr
    assert marker.exists() and "worker lost" in r.stderr, r.stderr
    rows = [json.loads(x) for x in (tmp_path / "ray" / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["rollout/groups"] == SMALL["prompts_per_iteration"] and rows[-1]["rollout/failed_units"] == 0, rows
    a, b = _weights(tmp_path / "ref"), _weights(tmp_path / "ray")
    assert all(torch.equal(a[k], b[k]) for k in a)
