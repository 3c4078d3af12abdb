"""DAgger (issue 18.2): the expert starts from any feasible state and refuses others with the reason; the states
picked from a rollout; a tiny model's round writes relabelled shards `roken validate` accepts, with `source`
and `round`; a round interrupted after relabelling and resumed equals an uninterrupted one."""
import copy
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import cli
import torch
from safetensors.torch import load_file

from roken.config import load_config
from roken.dagger import run_dagger, select_states
from roken.dagger.rounds import round_config
from roken.dagger.relabel import constraint_steps, feasible_steps
from roken.data.store import read_run
from roken.expert.laplacian import ExpertConfig, LaplacianExpert
from roken.train.data import load_banks
from roken.train.loop import Pretraining, PretrainSpec
from roken.units import InProcessRunner
from roken.world.maps import MapConfig, generate_map
from roken.world.tasks import Task, TaskConfig, TaskError, sample_task

ROOT = Path(__file__).resolve().parents[1]
TINY = ["model.width=64", "model.depth=2", "model.heads=4", "model.mlp_hidden=128", "model.map_channels=16",
        "model.map_blocks=1", "model.map_encoder=patch", "train.batch_size=4", "train.loader_workers=0",
        "train.val_fraction=0.34", "train.val_prompts=2", "train.log_every=1", "train.warmup_steps=0",
        "train.closed_loop_every=0", "train.closed_loop_tasks=2", "train.closed_loop_robots=2",
        "dagger.rounds=1", "dagger.episodes=3", "dagger.robots=2", "dagger.steps_per_round=2",
        "dagger.state_every=12", "dagger.max_states=3", "dagger.sample_steps=16", "plan.steps=2"]


def test_constraint_steps_say_which_constraint_each_state_breaks():
    tc, gm = TaskConfig(), generate_map(MapConfig(), "train", 3)
    task = sample_task(gm, 3, tc, np.random.default_rng(0))
    _, ep = next(LaplacianExpert(ExpertConfig(), tc).run([task], {gm.map_id: gm}))
    ok = np.stack([ep.positions[40]] * 4).astype(np.float64)
    ok[1, 1] = ok[1, 0] + [1.0, 0.0]  # two robots 1 m apart (d_coll_min = 2)
    ok[2, 2] = ok[2, 0] + [0.0, 0.0]  # on top of each other: spacing again
    far = ok[3].copy()
    far[2] = far[0] + 3.0 * tc.comm_radius * (far[2] - far[0]) / np.linalg.norm(far[2] - far[0])
    ok[3] = far  # one robot out of every other's reach (possibly in an obstacle as well)
    got = constraint_steps(np.concatenate([ep.positions[:1], ok]), gm, tc)
    assert got.shape == (3, 5) and got[:, 0].all()
    assert not got[1, 2] and not got[1, 3] and got[2, 2]
    assert not got[2, 4] and got[1, 4]
    np.testing.assert_array_equal(feasible_steps(np.concatenate([ep.positions[:1], ok]), gm, tc), got.all(axis=0))


def test_expert_refuses_an_infeasible_start_and_leaves_a_feasible_one_cleanly():
    tc, gm = TaskConfig(), generate_map(MapConfig(), "train", 3)
    task = sample_task(gm, 3, tc, np.random.default_rng(0))
    expert = LaplacianExpert(ExpertConfig(), tc)
    _, ep = next(expert.run([task], {gm.map_id: gm}))
    mid = ep.positions[40].astype(np.float64)  # a state of a clean run, not a sampled start
    assert feasible_steps(ep.positions, gm, tc).all()
    _, cont = next(expert.run([Task(gm.map_id, mid, task.goal, task.leader)], {gm.map_id: gm}))
    np.testing.assert_allclose(cont.positions[0], mid, atol=1e-5)
    assert feasible_steps(cont.positions[:65], gm, tc).all()  # at least one chunk horizon (16 x 4 steps) clean
    bad = mid.copy()
    bad[1] = bad[0] + [1.0, 0.0]  # two robots 1 m apart (d_coll_min = 2)
    with pytest.raises(TaskError, match="cannot start there: two robots start 1.00 m apart"):
        next(expert.run([Task(gm.map_id, bad, task.goal, task.leader)], {gm.map_id: gm}))


def test_states_are_the_last_feasible_one_and_those_before_it():
    tc, gm = TaskConfig(), generate_map(MapConfig(), "train", 3)
    task = sample_task(gm, 2, tc, np.random.default_rng(1))
    T = 100
    P = np.repeat(task.starts[None], T + 1, axis=0)
    P[70:, 1] = P[70:, 0] + [0.5, 0.0]  # robots collide from step 70 on
    steps = select_states(P, gm, task.goal, task.leader, tc, every=20, max_states=3)
    assert steps == [40, 60, 69]
    assert select_states(P[:60], gm, task.goal, task.leader, tc, every=20, max_states=5) == [20, 40]


def _tiny_model(expert_dataset, out: Path) -> str:
    cfg = load_config(None, TINY + ["train.steps=2"])
    Pretraining(PretrainSpec.of(cfg), expert_dataset, out).fit()
    return str(out)


def _run(cfg, model, data, out, train=None):
    def fit(c, datasets, shares, run_dir, val_data, init):
        return Pretraining(PretrainSpec.of(c), datasets, run_dir, val_data, data_shares=shares, init=init).fit()
    return run_dagger(cfg, model, data, out, InProcessRunner, train or fit, log=lambda m: None)


def test_a_round_writes_valid_relabelled_shards_and_resumes_exactly(expert_dataset, tmp_path):
    model = _tiny_model(expert_dataset, tmp_path / "pre")
    cfg = load_config(None, TINY + ["dagger.num_maps=1"])  # every rollout on the first train map
    a = _run(cfg, model, expert_dataset, tmp_path / "a")
    data = tmp_path / "a" / "round-00" / "data"
    maps, rollouts = read_run(tmp_path / "a" / "round-00" / "rollouts")
    assert len(rollouts) == cfg.dagger.episodes and {e["map_id"] for e in rollouts} == set(maps) == {"train-000000"}
    r = cli("roken", "validate", str(data))
    assert r.returncode == 0 and "manifest finished" in r.stdout, r.stderr
    tab = pq.read_table(data / "episodes" / "relabel.parquet")
    assert tab.num_rows == a["rounds"][0]["states"] > 0
    assert set(tab.column("source").to_pylist()) == {"dagger"} and set(tab.column("round").to_pylist()) == {0}
    assert a["rounds"][0]["shares"][0] == pytest.approx(1 - cfg.dagger.share)
    assert set(tab.column("sample_until").to_pylist()) == {16}
    bank, _, weights = load_banks([expert_dataset, str(data)], 140, shares=[0.5, 0.5])
    relabelled = np.array([e.startswith("dagger-") for e in bank.episode_ids])
    assert (bank.sample_until[relabelled] == 16).all() and (bank.sample_until[~relabelled] == bank.num_steps[~relabelled]).all()
    assert weights[relabelled].sum() == pytest.approx(weights[~relabelled].sum())  # the configured shares

    def interrupt(*_):  # the round stops in its training stage, after rollouts and relabelling
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        _run(copy.deepcopy(cfg), model, expert_dataset, tmp_path / "b", interrupt)
    assert not (tmp_path / "b" / "round-00" / "summary.json").exists()
    b = _run(copy.deepcopy(cfg), model, expert_dataset, tmp_path / "b")
    assert (tmp_path / "b" / "round-00" / "data" / "episodes" / "relabel.parquet").read_bytes() == \
        (data / "episodes" / "relabel.parquet").read_bytes()
    wa = load_file(str(Path(a["checkpoint"]) / "model.safetensors"))  # (the header's metadata order may vary)
    wb = load_file(str(Path(b["checkpoint"]) / "model.safetensors"))
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    again = _run(copy.deepcopy(cfg), model, expert_dataset, tmp_path / "b")  # finished: nothing re-run
    assert again["rounds"] == b["rounds"]
    with pytest.raises(ValueError, match="dagger.share"):
        _run(load_config(None, TINY + ["dagger.num_maps=1", "dagger.share=0.25"]), model, expert_dataset,
             tmp_path / "b")
    with pytest.raises(ValueError, match="dagger.num_maps=0"):
        _run(load_config(None, TINY + ["dagger.num_maps=0"]), model, expert_dataset, tmp_path / "c")


def test_only_failed_rollouts_are_relabelled_when_asked_and_the_planner_must_be_a_roken_row():
    from roken.dagger.relabel import DaggerConfig, check, relabel

    tc, gm = TaskConfig(), generate_map(MapConfig(), "train", 3)
    task = sample_task(gm, 2, tc, np.random.default_rng(1))
    P = np.repeat(task.starts[None], 61, axis=0)  # a team that holds for 60 steps (a stall)
    eps = [{"map_id": gm.map_id, "positions": P, "goal": task.goal, "leader": task.leader, "episode_id": f"e{i}",
            "seed": i, "success": i == 0} for i in range(2)]
    dc = DaggerConfig(state_every=20, max_states=2)
    every, _ = relabel(eps, {gm.map_id: gm}, 0, dc, tc, ExpertConfig())
    failed, stats = relabel(eps, {gm.map_id: gm}, 0, DaggerConfig(state_every=20, max_states=2, only_failed=True),
                            tc, ExpertConfig())
    assert len(every) == 4 and len(failed) == stats["states"] == 2
    assert all("-e1-" in r["episode_id"] for r in failed)
    check(DaggerConfig(planner="roken+guided+geodesic"))
    with pytest.raises(ValueError, match="dagger.planner"):
        check(DaggerConfig(planner="laplacian"))


def test_rollouts_take_new_tasks_each_round_or_round_zeros_with_same_tasks():
    from roken.dagger.relabel import DaggerConfig
    from roken.dagger.rounds import rollout_seed

    assert len({rollout_seed(DaggerConfig(), r) for r in range(5)}) == 5
    assert {rollout_seed(DaggerConfig(same_tasks=True), r) for r in range(5)} == {rollout_seed(DaggerConfig(), 0)}
    assert rollout_seed(DaggerConfig(seed=1), 0) != rollout_seed(DaggerConfig(seed=0), 0)


@pytest.mark.parametrize("recipe", sorted(p.name for p in (ROOT / "configs" / "dagger").glob("*.yaml")))
def test_every_dagger_recipe_loads_and_passes_the_checks(recipe):
    from roken.dagger.relabel import check

    cfg = load_config(str(ROOT / "configs" / "dagger" / recipe), [])
    check(cfg.dagger)
    assert cfg.dagger.planner.startswith("roken")


def test_successful_rollouts_are_kept_as_executed_with_keep_success():
    from roken.dagger.relabel import DaggerConfig, relabel

    tc, gm = TaskConfig(), generate_map(MapConfig(), "train", 3)
    task = sample_task(gm, 2, tc, np.random.default_rng(1))
    (_, e), = list(LaplacianExpert(ExpertConfig(), tc).run([task], {gm.map_id: gm}))
    assert e.reached
    held = np.repeat(task.starts[None], 61, axis=0)
    eps = [{"map_id": gm.map_id, "positions": p, "goal": task.goal, "leader": task.leader, "episode_id": f"e{i}",
            "num_robots": 2, "seed": i, "success": ok} for i, (p, ok) in enumerate([(e.positions, True),
                                                                                  (held, False)])]
    dc = DaggerConfig(state_every=20, max_states=2, only_failed=True, keep_success=True)
    rows, stats = relabel(eps, {gm.map_id: gm}, 3, dc, tc, ExpertConfig())
    own = [r for r in rows if r["source"] == "self"]
    assert stats["self"] == len(own) == 1 and len(rows) == stats["states"] + 1
    assert own[0]["success"] and own[0]["round"] == 3 and own[0]["episode_id"] == "self-r03-e0"
    np.testing.assert_allclose(own[0]["positions"], e.positions)  # as executed, not relabelled
    rows, stats = relabel(eps, {gm.map_id: gm}, 3, DaggerConfig(state_every=20, max_states=2, only_failed=True),
                          tc, ExpertConfig())
    assert stats["self"] == 0 and all(r["source"] == "dagger" for r in rows)


def test_relabels_can_carry_the_learners_last_moves_as_history():
    """dagger.history_steps: a relabelled episode begins with the rollout's last steps before its state, its chunks
    start at that state (sample_from), so a last-move model's sample there reads the learner's own last move."""
    from roken.dagger.relabel import DaggerConfig, relabel
    from roken.data.samples import EpisodeBank, SampleConfig, make_sample
    from roken.data.store import episodes_table, maps_table

    tc, gm = TaskConfig(), generate_map(MapConfig(), "train", 3)
    task = sample_task(gm, 3, tc, np.random.default_rng(0))
    _, ep = next(LaplacianExpert(ExpertConfig(), tc).run([task], {gm.map_id: gm}))
    P = ep.positions[:81].astype(np.float64)  # a rollout that moves and timed out (relabelled)
    eps = [{"map_id": gm.map_id, "positions": P, "goal": task.goal, "leader": task.leader, "episode_id": "e0",
            "seed": 0, "success": False}]
    dc = DaggerConfig(state_every=20, max_states=2, history_steps=4, sample_steps=16)
    rows, stats = relabel(eps, {gm.map_id: gm}, 0, dc, tc, ExpertConfig())
    plain, _ = relabel(eps, {gm.map_id: gm}, 0, DaggerConfig(state_every=20, max_states=2), tc, ExpertConfig())
    assert len(rows) == len(plain) == stats["states"] == 2
    for r, q in zip(rows, plain):
        t = int(r["episode_id"].rsplit("-t", 1)[1])
        np.testing.assert_allclose(r["positions"][:5], P[t - 4:t + 1], atol=1e-5)  # the learner's steps, then t
        np.testing.assert_allclose(r["positions"][4:], q["positions"], atol=1e-5)  # the same expert continuation
        assert (r["sample_from"], r["sample_until"], q["sample_from"], q["sample_until"]) == (4, 20, 0, 0)
    bank = EpisodeBank.from_arrow(episodes_table(rows), maps_table([gm]))
    cfg = SampleConfig(augment=False, shuffle_robots=False, condition_prob=0.0, subteam_prob=0.0)

    class Spy:  # records the sampler's integer draws (the chunk time is the first); `first` forces that one
        def __init__(self, seed, first=None):
            self.g, self.calls, self.first = np.random.default_rng(seed), [], first

        def integers(self, *a, **kw):
            self.calls.append(a)
            if len(self.calls) == 1 and self.first is not None:
                return self.first
            return self.g.integers(*a, **kw)

        def __getattr__(self, name):
            return getattr(self.g, name)

    for seed in range(5):
        rng = Spy(seed)
        make_sample(bank, 0, rng, cfg)
        assert rng.calls[0][:2] == (4, 20), "chunks start at the relabelled state, within sample_steps of it"
    t = int(rows[0]["episode_id"].rsplit("-t", 1)[1])
    s = make_sample(bank, 0, Spy(0, first=4), cfg)  # the chunk at the relabelled state
    np.testing.assert_allclose(s["prev_move"][:3], (P[t] - P[t - 4]) / cfg.step_scale, atol=1e-5)
    assert np.abs(s["prev_move"][:3]).max() > 0.05, "the learner moved into the state: not the at-rest zero"


def test_a_round_with_the_selfcost_term_reads_the_learners_own_rollouts(expert_dataset, tmp_path):
    model = _tiny_model(expert_dataset, tmp_path / "pre")
    cfg = load_config(None, TINY + ["selfcost.weight=0.1", "selfcost.prompts=2", "selfcost.candidates=2",
                                    "selfcost.steps=2", "selfcost.state_every=4"])
    a = _run(cfg, model, expert_dataset, tmp_path / "a")
    from roken.train import checkpoint as ckpt
    used = ckpt.read_config(a["checkpoint"])
    assert used["selfcost"]["states"] == str(tmp_path / "a" / "round-00" / "rollouts")  # every round so far
    assert round_config(cfg, model, tmp_path / "a", 2).selfcost.states.split(",") == \
        [str(tmp_path / "a" / f"round-{k:02d}" / "rollouts") for k in range(3)]
    assert round_config(load_config(None, TINY), model, tmp_path / "a", 2).selfcost.states == ""  # off: none
