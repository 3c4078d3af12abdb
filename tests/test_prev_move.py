"""The last-move input (model.prev_move): what samples, the planner and the closed loop feed it, that a model
without it ignores it, and that a run adding it starts from a checkpoint without it unchanged."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from roken.config import load_config
from roken.data.condition import build_condition
from roken.data.loader import collate
from roken.data.samples import EpisodeBank, SampleConfig, make_sample
from roken.eval.harness import make_tasks
from roken.model.diffusion import COND_KEYS, DiffusionConfig, NoiseSchedule
from roken.model.dit import RokenDiT, preset
from roken.plan import PlanConfig, RokenPlanner, RokenRollout
from roken.train.data import SampleStream
from roken.train.loop import Pretraining, PretrainSpec
from roken.world.maps import generate_map

PLAIN = SampleConfig(augment=False, shuffle_robots=False, condition_prob=0.0, final_goal_prob=1.0)
TINY = ["model.width=64", "model.depth=2", "model.heads=4", "model.mlp_hidden=128", "model.map_channels=16",
        "model.map_blocks=1", "train.batch_size=4", "train.loader_workers=0", "train.val_fraction=0.34",
        "train.val_prompts=4", "train.log_every=1", "train.warmup_steps=2", "train.closed_loop_every=0"]


def test_samples_carry_the_move_one_interval_back_and_rotate_with_the_map(expert_dataset):
    bank = EpisodeBank.from_folder(expert_dataset)
    for i in range(len(bank)):
        s = make_sample(bank, i, np.random.default_rng(i), PLAIN)
        P, N = bank.positions(i), int(s["num_robots"])
        ts = np.flatnonzero(np.abs(P - s["start"][:N]).max(axis=(1, 2)) == 0)
        want = [(P[t] - P[max(0, t - PLAIN.interval)]) / PLAIN.step_scale for t in ts]
        assert any(np.allclose(s["prev_move"][:N], w, atol=1e-5) for w in want)
        assert not s["prev_move"][N:].any()
        # augmented: the same move turned with the map (a norm-preserving map of the plain one)
        a = make_sample(bank, i, np.random.default_rng(i), replace(PLAIN, augment=True))
        np.testing.assert_allclose(np.linalg.norm(a["prev_move"][:N], axis=-1),
                                   np.linalg.norm(s["prev_move"][:N], axis=-1), atol=1e-5)
    noisy = make_sample(bank, 0, np.random.default_rng(0), replace(PLAIN, prev_noise=0.3))
    clean = make_sample(bank, 0, np.random.default_rng(0), PLAIN)
    N = int(clean["num_robots"])
    assert not np.allclose(noisy["prev_move"][:N], clean["prev_move"][:N]) and not noisy["prev_move"][N:].any()
    np.testing.assert_array_equal(noisy["chunk"], clean["chunk"])


def test_condition_builder_scales_the_last_move_like_a_chunk():
    occ = np.zeros((140, 140), np.uint8)
    pos = np.array([[10.0, 10.0], [20.0, 20.0]])
    c = build_condition(occ, pos, 0, np.array([50.0, 50.0]), SampleConfig(), previous=pos - [[2.0, 0.0], [0, -1]])
    np.testing.assert_allclose(c["prev_move"][:2], [[1.0, 0.0], [0.0, -0.5]])  # 2 m = a full-speed chunk move
    assert not c["prev_move"][2:].any()
    assert not build_condition(occ, pos, 0, None, SampleConfig())["prev_move"].any()  # None: at rest


def test_the_input_is_ignored_without_the_option_and_enters_at_zero_with_it(expert_dataset):
    ds = SampleStream(EpisodeBank.from_folder(expert_dataset), SampleConfig(), seed=0)
    batch = collate([ds[g] for g in range(3)])
    cond = {k: batch[k] for k in COND_KEYS + ("map",)}
    assert cond["prev_move"].abs().sum() > 0
    x, k = torch.randn_like(batch["chunk"]), torch.tensor([3, 40, 90])
    torch.manual_seed(0)
    off = RokenDiT(preset("tiny")).eval()
    torch.manual_seed(0)
    on = RokenDiT(preset("tiny", prev_move=True)).eval()
    for m in (off, on):
        torch.nn.init.normal_(m.final.linear.weight, std=0.1)
    on.load_state_dict(off.state_dict(), strict=False)
    zero = cond | {"prev_move": torch.zeros_like(cond["prev_move"])}
    with torch.no_grad():
        base = off(x, k, cond)["eps"]
        assert torch.equal(base, off(x, k, zero)["eps"]), "a model without the option never reads the input"
        torch.testing.assert_close(on(x, k, cond)["eps"], base)  # zero-initialised: the same function at first
        torch.nn.init.normal_(on.phi_prev.weight, std=0.5)
        assert not torch.allclose(on(x, k, cond)["eps"], on(x, k, zero)["eps"])


def spy_prev_moves(planner: RokenPlanner) -> list:
    """The prev_move inputs (B, R, 2) of each of planner's sample() calls, appended as they come."""
    seen, sample = [], planner.sample

    def spy(conds, *a, **kw):
        seen.append(np.stack([c["prev_move"] for c in conds]))
        return sample(conds, *a, **kw)

    planner.sample = spy
    return seen


def test_closed_loop_feeds_the_executed_move_one_interval_back():
    cfg = load_config(None, ["eval.episodes=2"])
    maps = [generate_map(cfg.map, "eval", i) for i in range(2)]
    tasks, _ = make_tasks(cfg, maps, 2)
    torch.manual_seed(0)
    model = RokenDiT(preset("tiny", prev_move=True))
    for p in model.final.parameters():
        torch.nn.init.normal_(p, std=0.5)
    planner = RokenPlanner(model, NoiseSchedule(DiffusionConfig(num_steps=20)), SampleConfig(), "cpu")
    seen = spy_prev_moves(planner)
    ro = RokenRollout(planner, PlanConfig(batch_size=1, device="cpu"), cfg.task, cfg.expert)
    (_, hist, info), = [r for r in ro.run([tasks[0][1]], {m.map_id: m for m in maps}) if r[0] == 0]
    N, iv = hist.shape[1], SampleConfig().interval
    assert not seen[0].any(), "the first plan starts at rest"
    for j, t in enumerate(info["plan_steps"][1:], start=1):
        want = (hist[t].astype(np.float64) - hist[t - iv]) / SampleConfig().step_scale
        np.testing.assert_allclose(seen[j][0, :N], want, atol=1e-5)
    assert np.abs(seen[-1]).max() > 0.05, "the random model moves, so the input is not all zero"


@pytest.mark.parametrize("option,prefix", [("model.prev_move=true", "phi_prev."), ("model.neighbours=2", "phi_nbr.")])
def test_a_run_adding_the_input_starts_from_a_checkpoint_without_it(expert_dataset, tmp_path, option, prefix):
    # the zero-initialised inputs (the last move; the team-mates' offsets, tests/test_neighbours.py)
    base = Pretraining(PretrainSpec.of(load_config(None, TINY + ["train.steps=3"])), expert_dataset, tmp_path / "a")
    base.fit()
    run = Pretraining(PretrainSpec.of(load_config(None, TINY + ["train.steps=6", option])),
                      expert_dataset, tmp_path / "b", init=str(tmp_path / "a"))
    run._build()
    run._load_init(str(tmp_path / "a"))
    for name, v in base.model.state_dict().items():
        assert torch.equal(run.model.state_dict()[name], v), name
    own = dict(run.model.named_parameters())
    added = [p for n, p in own.items() if n.startswith(prefix)]
    assert added and not added[-1].any(), "the new input's output layer starts at 0"
    # AdamW's moments follow each parameter by name (the new input's are fresh)
    old = dict(base.model.named_parameters())
    for name in ("phi_tau.weight", "blocks.0.mlp.0.bias", "final.linear.weight"):
        torch.testing.assert_close(run.opt.state[own[name]]["exp_avg"], base.opt.state[old[name]]["exp_avg"])
    assert all(p not in run.opt.state for p in added)
    assert run.fit()["steps"] == 6
    trained = [p for n, p in run.model.named_parameters() if n.startswith(prefix)]  # fit() builds the model anew
    assert trained[-2].abs().sum() > 0, "the new input learns"


def test_a_prefix_hands_the_episode_over_at_its_last_row():
    """RokenRollout.run(prefixes=...) (benchmarks/start_handoff.py): the expert's first K steps are kept as they
    are, the first plan is made from their last row with their last move as history, an episode whose prefix
    already reached the goal is returned untouched, and a prefix from elsewhere is refused."""
    import pytest

    from roken.expert.laplacian import LaplacianExpert
    cfg = load_config(None, ["eval.episodes=2"])
    maps = [generate_map(cfg.map, "eval", i) for i in range(2)]
    by_id = {m.map_id: m for m in maps}
    task = make_tasks(cfg, maps, 2)[0][0][1]
    (_, ep), = list(LaplacianExpert(cfg.expert, cfg.task).run([task], by_id))
    K = 12
    torch.manual_seed(0)
    planner = RokenPlanner(RokenDiT(preset("tiny", prev_move=True)), NoiseSchedule(DiffusionConfig(num_steps=20)),
                           SampleConfig(), "cpu")
    seen = spy_prev_moves(planner)
    ro = RokenRollout(planner, PlanConfig(batch_size=2, device="cpu"), cfg.task, cfg.expert)
    out = {i: (p, info) for i, p, info in ro.run([task, task], by_id, [ep.positions[:K + 1], ep.positions])}
    hist, info = out[0]
    np.testing.assert_array_equal(hist[:K + 1], ep.positions[:K + 1].astype(np.float32))
    assert info["plan_steps"][0] == K and len(hist) > K + 1
    N, iv = hist.shape[1], SampleConfig().interval
    want = (hist[K].astype(np.float64) - hist[K - iv]) / SampleConfig().step_scale
    np.testing.assert_allclose(seen[0][0, :N], want, atol=1e-5)
    assert np.abs(want).max() > 0.05, "the expert moves in its first steps, so the history is not all zero"
    whole, info = out[1]
    np.testing.assert_array_equal(whole, ep.positions.astype(np.float32))
    assert info["plan_steps"] == [], "an episode its prefix finished is not planned"
    with pytest.raises(ValueError, match="does not start at the task's starts"):
        list(ro.run([task], by_id, [ep.positions[3:K]]))
