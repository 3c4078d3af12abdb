"""The constraint cost of the model's own samples (roken/rl/selfcost.py): its states are the feasible ones of the
rollouts given, a step's draws depend only on the step (a resumed run repeats them), descending it lowers the
cost of the model's samples, and a pretraining run carries it beside the denoising loss."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from roken.config import load_config
from roken.dagger.relabel import feasible_steps
from roken.model.diffusion import NoiseSchedule
from roken.model.dit import RokenDiT
from roken.rl.selfcost import SelfCost, SelfCostConfig, check, visited_states
from roken.train.loop import Pretraining, PretrainSpec

ROOT = Path(__file__).resolve().parents[1]
TINY = ["model.width=64", "model.depth=2", "model.heads=4", "model.mlp_hidden=128", "model.map_channels=16",
        "model.map_blocks=1", "model.map_encoder=patch", "train.batch_size=4", "train.loader_workers=0",
        "train.val_fraction=0.34", "train.val_prompts=2", "train.log_every=1", "train.warmup_steps=0",
        "train.closed_loop_every=0", "train.eval_every=0", "selfcost.prompts=3", "selfcost.candidates=2",
        "selfcost.steps=3", "selfcost.grad_steps=1", "selfcost.state_every=16"]


def descend(term, model, sched, step: int, lr: float, iters: int = 5) -> torch.Tensor:
    """`iters` Adam steps on the term at one step's draws; the term there afterwards."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    for _ in range(iters):
        loss, _ = term(model, sched, step=step)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return term(model, sched, step=step)[0]


def test_the_states_are_the_feasible_ones_of_the_rollouts(expert_dataset):
    cfg = load_config(None, TINY)
    maps, episodes, states = visited_states([expert_dataset], cfg.task, 16)
    assert states and all(t % 16 == 0 for _, t in states)
    for e, t in states:
        ep = episodes[e]
        assert feasible_steps(np.asarray(ep["positions"]), maps[ep["map_id"]], cfg.task)[t]
    with pytest.raises(ValueError, match="selfcost.states"):
        check(SelfCostConfig(weight=1.0))
    with pytest.raises(ValueError, match="selfcost.candidates"):
        check(SelfCostConfig(weight=1.0, states=expert_dataset, candidates=0))


def test_descending_the_term_lowers_the_cost_of_the_models_own_samples(expert_dataset):
    cfg = load_config(None, TINY + [f"selfcost.states={expert_dataset}", "selfcost.weight=1", "selfcost.goal=0",
                                    "selfcost.grad_steps=1"])
    torch.manual_seed(0)
    model = RokenDiT(cfg.model)
    sched = NoiseSchedule(cfg.diffusion)
    term = SelfCost(cfg.selfcost, cfg.samples, cfg.plan, cfg.task)
    first, logs = term(model, sched, step=7)
    again, _ = term(model, sched, step=7)
    assert first.item() == pytest.approx(again.item(), rel=1e-5)  # a step's draws come from the step alone
    assert {"losses/selfcost", "selfcost/violating"} <= set(logs) and first.item() > 0
    first.backward()
    assert sum(float(p.grad.norm()) for p in model.parameters() if p.grad is not None) > 0
    after = descend(term, model, sched, step=7, lr=3e-3)  # the same draws every time: their cost must fall
    # (an untrained model's clean chunks sit on the sampler's clip, where they have no gradient: a part of the cost
    # cannot move; measured 674 -> 606)
    assert after.item() < 0.95 * first.item()


def test_a_pretraining_run_carries_the_term(expert_dataset, tmp_path):
    cfg = load_config(None, TINY + ["train.steps=2", f"selfcost.states={expert_dataset}", "selfcost.weight=0.1"])
    summary = Pretraining(PretrainSpec.of(cfg), expert_dataset, tmp_path / "run").fit()
    assert summary["steps"] == 2 and summary["final"]["losses/selfcost"] > 0
    from roken.train import checkpoint as ckpt
    assert ckpt.read_config(summary["checkpoint"])["selfcost"]["weight"] == 0.1


@pytest.mark.parametrize("script,extra", [("pretrain.py", []),
                                          ("dagger.py", ["--checkpoint", str(ROOT / "models" / "roken-cpu-four")])])
def test_the_pipelines_name_a_bad_states_folder_before_writing(expert_dataset, tmp_path, script, extra):
    from conftest import cli
    args = ["--data", expert_dataset, "--out", str(tmp_path / "out"), "--workers", "0", "--set", "selfcost.weight=0.1",
            "--set", f"selfcost.states={tmp_path / 'missing'}"] + extra
    r = cli(script, *args)
    assert r.returncode == 2 and "selfcost.states" in r.stderr and "is not a folder of closed-loop rollouts" in r.stderr, \
        r.stderr
    assert not (tmp_path / "out").exists()
    r = cli("pretrain.py", *args[:6], "--set", "selfcost.weight=0.1")  # on, but no states given
    assert r.returncode == 2 and "needs selfcost.states" in r.stderr, r.stderr


def test_the_guided_target_pulls_the_models_samples_onto_their_guided_version(expert_dataset):
    from roken.train import checkpoint as ckpt
    cfg = load_config(None, TINY + [f"selfcost.states={expert_dataset}", "selfcost.distil=1",
                                    "plan.guide_iters=2", "plan.guide_final_iters=5"])
    # a trained model (an untrained one's clean chunks sit on the sampler's clip, where nothing can move them)
    loaded = ckpt.load(ckpt.find(ROOT / "models" / "roken-cpu-four"), "cpu")
    model, sched = loaded.model.train(), loaded.schedule
    term = SelfCost(cfg.selfcost, loaded.samples, cfg.plan, cfg.task)
    first, logs = term(model, sched, step=3)
    again, _ = term(model, sched, step=3)
    assert first.item() == pytest.approx(again.item(), rel=1e-5)  # the target is as repeatable as the sample
    assert {"losses/distil", "selfcost/violating", "selfcost/target_violating"} <= set(logs) and "losses/selfcost" not in logs
    assert 0 <= logs["selfcost/target_violating"].item() < 1 and first.item() > 0
    after = descend(term, model, sched, step=3, lr=1e-4)  # the target moves with the model; the distance must fall
    assert after.item() < 0.7 * first.item()
    with pytest.raises(ValueError, match="selfcost.distil"):
        check(SelfCostConfig(distil=-1.0, states=expert_dataset))
    with pytest.raises(ValueError, match="needs selfcost.states"):
        check(SelfCostConfig(distil=1.0))


def test_no_feasible_target_gives_no_pull(expert_dataset):
    cfg = load_config(None, TINY + [f"selfcost.states={expert_dataset}", "selfcost.distil=1",
                                    "plan.guide_iters=1", "plan.guide_final_iters=1"])
    torch.manual_seed(0)
    term = SelfCost(cfg.selfcost, cfg.samples, cfg.plan, cfg.task)
    term.tc = replace(cfg.task, d_obs_min=1000.0)  # (after the states are read) every point is too near an obstacle
    loss, logs = term(RokenDiT(cfg.model), NoiseSchedule(cfg.diffusion), step=0)
    assert loss.item() == 0 and logs["selfcost/target_violating"].item() == 1


def test_the_cost_and_the_guided_target_add_up(expert_dataset):
    from roken.train import checkpoint as ckpt
    cfg = load_config(None, TINY + [f"selfcost.states={expert_dataset}", "selfcost.distil=2", "selfcost.weight=0.1",
                                    "plan.guide_iters=1", "plan.guide_final_iters=2"])
    loaded = ckpt.load(ckpt.find(ROOT / "models" / "roken-cpu-four"), "cpu")
    loss, logs = SelfCost(cfg.selfcost, loaded.samples, cfg.plan, cfg.task)(loaded.model, loaded.schedule, step=1)
    assert loss.item() == pytest.approx(0.1 * logs["losses/selfcost"].item() + 2 * logs["losses/distil"].item(),
                                        rel=1e-4)


def test_the_pace_hinge_pulls_only_a_leader_behind_schedule(expert_dataset):
    from roken.plan.guidance import finite_geodesic
    cfg = load_config(None, TINY + [f"selfcost.states={expert_dataset}", "selfcost.weight=1", "selfcost.pace=0.25"])
    term = SelfCost(cfg.selfcost, cfg.samples, cfg.plan, cfg.task)
    geo = torch.from_numpy(finite_geodesic(np.zeros((140, 140), bool), (120.0, 70.0)))[None].repeat(3, 1, 1)
    H, step = cfg.samples.horizon, cfg.samples.interval
    start = torch.tensor([[20.0, 70.0], [20.0, 40.0]]).repeat(3, 1, 1)  # (3, R=2, 2): robot 0 leads
    t = step * torch.arange(1, H + 1, dtype=torch.float32)
    speed = torch.tensor([0.5, 0.25, 0.0])[:, None, None]  # m per simulator step toward the goal (+x)
    p = start[:, :, None].repeat(1, 1, H, 1)  # (3, 2, H, 2)
    p[:, 0, :, 0] += (speed[:, 0] * t)
    lag = term.behind(p, start, geo, torch.zeros(3, dtype=torch.long))
    assert lag[0].item() == pytest.approx(0, abs=0.05) and lag[1].item() == pytest.approx(0, abs=0.05)
    # standing still: behind by pace * t at every point, mean over the chunk
    assert lag[2].item() == pytest.approx(float((0.25 * t).mean()), rel=0.02)
    with pytest.raises(ValueError, match="selfcost.pace"):
        check(SelfCostConfig(weight=1.0, states=expert_dataset, pace=-1))


def test_spacing_moves_the_inter_robot_hinge_out(expert_dataset):
    cfg = load_config(None, TINY + [f"selfcost.states={expert_dataset}", "selfcost.weight=1", "selfcost.goal=0",
                                    "selfcost.candidates=1"])
    H = cfg.samples.horizon
    start = np.array([[[50.0, 50.0], [53.0, 50.0]]], np.float32)  # two robots 3 m apart, in the open
    p = torch.from_numpy(start)[:, :, None].repeat(1, 1, H, 1)  # standing still
    fields = (start, np.ones((1, 2), bool), np.zeros(1, np.int64), np.full((1, 140, 140), 50.0, np.float32),
              np.zeros((1, 140, 140), np.float32))
    costs = []
    for spacing in (0.0, 0.8):
        cfg.selfcost.spacing = spacing
        costs.append(SelfCost(cfg.selfcost, cfg.samples, cfg.plan, cfg.task).costed(p, p[:, :, 0], fields).item())
    assert costs[0] == 0 < costs[1]  # 3 m clears 2 m + the 0.6 m margin, not 2.8 m + 0.6 m
