"""Pretraining in-process: the loop learns, checkpoints round-trip bit-exact, resume continues exactly, bad
inputs fail early with the file and the fix, and --shard runs make the same dataset as one run."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
from conftest import cli
from safetensors.torch import load_file

from roken.config import load_config
from roken.data.loader import collate
from roken.data.samples import EpisodeBank, SampleConfig, make_sample
from roken.train import checkpoint as ckpt
from roken.train.data import SampleStream, StepIndices
from roken.train.loop import Pretraining, PretrainSpec

ROOT = Path(__file__).resolve().parents[1]
TINY = ["model.width=64", "model.depth=2", "model.heads=4", "model.mlp_hidden=128", "model.map_channels=16",
        "model.map_blocks=1", "train.batch_size=4", "train.loader_workers=0", "train.val_fraction=0.34",
        "train.val_prompts=4", "train.log_every=1", "train.warmup_steps=2",
        "train.closed_loop_every=0"]  # closed-loop validation has its own tests (test_cpu_training.py)


def spec(*extra) -> PretrainSpec:
    return PretrainSpec.of(load_config(None, TINY + list(extra)))


def run_pipeline(*args) -> subprocess.CompletedProcess:
    return cli("pretrain.py", *args)


def test_loop_overfits_a_few_samples(expert_dataset, tmp_path):
    run = Pretraining(spec("train.lr=3e-3", "train.weight_decay=0", "loss.sdf=0", "loss.occ=0"),
                      expert_dataset, tmp_path)
    run._build()
    stream = SampleStream(run.train_bank, run.spec.samples, seed=0)
    batch = collate([stream[g] for g in range(4)])
    torch.manual_seed(0)
    first = [float(run.train_step(batch)["losses/traj"]) for _ in range(5)]
    for _ in range(250):
        logs = run.train_step(batch)
    last = np.mean([float(run.train_step(batch)["losses/traj"]) for _ in range(10)])
    assert last < 0.25 * np.mean(first), (first, last)
    assert float(logs["losses/wp"]) < 0.05


def test_checkpoint_round_trip_is_bit_exact_and_resume_continues_exactly(expert_dataset, tmp_path):
    straight = Pretraining(spec("train.steps=6", "train.checkpoint_every=3", "train.eval_every=3"),
                           expert_dataset, tmp_path / "a")
    summary = straight.fit()
    assert summary["steps"] == 6 and (tmp_path / "a" / "summary.json").is_file()
    last = tmp_path / "a" / "checkpoint-0000006"
    loaded = ckpt.load(tmp_path / "a")  # the run folder -> its latest checkpoint
    assert loaded.path == last
    for k, v in straight.ema.state_dict().items():
        assert torch.equal(loaded.model.state_dict()[k], v), k
    state = ckpt.load_train_state(last)
    assert state["step"] == 6 and torch.equal(state["model"]["phi_tau.weight"], straight.model.phi_tau.weight)
    cfg = json.loads((last / "config.json").read_text())
    assert {"model", "diffusion", "samples", "loss", "train", "task", "dataset", "code_version"} <= set(cfg)
    assert cfg["dataset"]["fingerprint"] and "val/model/obs_frac" in cfg["validation"]
    rows = [json.loads(x) for x in (tmp_path / "a" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2, 3, 4, 5, 6] and "losses/traj" in rows[0] and "val/still/l2_m" in rows[2]
    assert list((tmp_path / "a" / "tb").iterdir()), "TensorBoard event files"

    # A run killed after its step-3 checkpoint and started again ends with the same weights, bit for bit
    # (data position, optimizer, EMA and RNG restored); the metrics past step 3 are rewritten, not doubled.
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    shutil.rmtree(tmp_path / "b" / "checkpoint-0000006")
    resumed = Pretraining(spec("train.steps=6", "train.checkpoint_every=3", "train.eval_every=3"),
                          expert_dataset, tmp_path / "b")
    assert resumed.fit()["resumed_from"] == 3
    for k, v in straight.model.state_dict().items():
        assert torch.equal(resumed.model.state_dict()[k], v), k
    steps = [json.loads(x)["step"] for x in (tmp_path / "b" / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6]


def test_half_precision_shipping_and_load_errors_name_the_file(expert_dataset, tmp_path):
    run = Pretraining(spec("train.steps=2", "train.eval_every=0"), expert_dataset, tmp_path / "r")
    run.fit()
    src = tmp_path / "r" / "checkpoint-0000002"
    half = ckpt.save_atomic(tmp_path / "ship", 2, load_file(str(src / "model.safetensors")),
                            ckpt.read_config(src), half=True)
    assert load_file(str(half / "model.safetensors"))["phi_tau.weight"].dtype == torch.float16
    assert ckpt.load(half).model.phi_tau.weight.dtype == torch.float32

    bad = tmp_path / "corrupt"
    shutil.copytree(src, bad)
    data = (bad / "model.safetensors").read_bytes()
    (bad / "model.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(ckpt.CheckpointError, match="corrupt/model.safetensors"):
        ckpt.load(bad)
    (bad / "train_state.pt").write_bytes(b"not a zip")
    with pytest.raises(ckpt.CheckpointError, match="train_state.pt"):
        ckpt.load_train_state(bad)

    other = tmp_path / "other-size"
    shutil.copytree(src, other)
    cfg = json.loads((other / "config.json").read_text())
    cfg["model"]["width"] = 128
    (other / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ckpt.CheckpointError, match="other-size/model.safetensors: .*shape mismatch blocks.0"):
        ckpt.load(other)
    cfg["model"]["width"], cfg["samples"]["horizon"] = 64, 8
    (other / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ckpt.CheckpointError, match="samples.horizon=8 vs model.horizon=16"):
        ckpt.load(other)
    with pytest.raises(ckpt.CheckpointError, match="samples.max_step=0.5 vs task.max_step=0.25"):
        ckpt.load(src, task_max_step=0.25)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ckpt.CheckpointError, match="empty: no checkpoint in this folder"):
        ckpt.load(tmp_path / "empty")


def test_pipeline_bad_inputs_fail_before_writing(expert_dataset, tmp_path):
    r = run_pipeline("--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o1"), "--workers", "0")
    assert r.returncode == 2 and "no dataset there" in r.stderr and not (tmp_path / "o1").exists()
    failed = tmp_path / "failed"
    shutil.copytree(expert_dataset, failed)
    for f in (failed / "episodes").glob("*.parquet"):
        t = pq.read_table(f)
        pq.write_table(t.set_column(t.schema.get_field_index("success"), "success",
                                    pa.array([False] * t.num_rows)), f)
    r = run_pipeline("--data", str(failed), "--out", str(tmp_path / "o2"), "--workers", "0")
    assert r.returncode == 2 and "none of its" in r.stderr and not (tmp_path / "o2").exists()
    r = run_pipeline("--data", f"{expert_dataset},{expert_dataset}", "--data-shares", "1", "--out",
                     str(tmp_path / "o4"), "--workers", "0")  # several datasets: one share each
    assert r.returncode == 2 and "--data-shares 1" in r.stderr and not (tmp_path / "o4").exists()
    r = run_pipeline("--data", f"{expert_dataset},{expert_dataset}", "--data-shares", "0.7,0.3", "--out",
                     str(tmp_path / "mix"), "--workers", "0", "--steps", "1", "--preset", "tiny", "--set",
                     "train.batch_size=4", "--set", "train.loader_workers=0", "--set", "train.eval_every=0",
                     "--set", "train.closed_loop_every=0")
    assert r.returncode == 0, r.stderr  # ... and mixed as given
    meta = ckpt.read_config(ckpt.list_checkpoints(tmp_path / "mix")[-1])
    assert len(meta["dataset"]["datasets"]) == 2 and meta["data_shares"] == [0.7, 0.3]
    r = run_pipeline("--data", f"{expert_dataset},{tmp_path / 'nope'}", "--out", str(tmp_path / "o5"), "--workers", "0")
    assert r.returncode == 2 and "no dataset there" in r.stderr and not (tmp_path / "o5").exists()
    r = run_pipeline("--data", expert_dataset, "--out", str(tmp_path / "o3"), "--workers", "0",
                     "--set", "train.schedule=linear")
    assert r.returncode == 2 and "train.schedule" in r.stderr and not (tmp_path / "o3").exists()

    # An existing run made with another config is refused with the keys; its checkpoints are untouched.
    args = ["--data", expert_dataset, "--out", str(tmp_path / "run"), "--workers", "0", "--steps", "2",
            "--preset", "tiny", "--set", "train.batch_size=4", "--set", "train.loader_workers=0",
            "--set", "train.eval_every=0", "--set", "train.closed_loop_every=0"]  # (its own tests: test_cpu_training)
    assert run_pipeline(*args).returncode == 0
    before = (tmp_path / "run" / "checkpoint-0000002" / "model.safetensors").read_bytes()
    r = run_pipeline(*args, "--set", "loss.wp=0.5")
    assert r.returncode == 2 and "loss.wp: 1.0 -> 0.5" in r.stderr
    assert (tmp_path / "run" / "checkpoint-0000002" / "model.safetensors").read_bytes() == before
    r = run_pipeline(*[("4" if a == "2" else a) for a in args])  # --steps 4: the same run goes on from step 2
    assert r.returncode == 0 and "resuming at step 2" in r.stderr and "2 -> 4" in r.stdout


def test_step_indices_split_global_batches_over_workers():
    one = list(StepIndices(3, 5, 8))
    two = [list(StepIndices(3, 5, 8, rank=r, world=2)) for r in range(2)]
    assert one == list(range(24, 40))
    assert sorted(two[0] + two[1]) == one and two[0][:4] == [24, 25, 26, 27]
    with pytest.raises(ValueError, match="not divisible"):
        StepIndices(0, 1, 6, 0, 4)


def test_goals_reach_far_and_subteams_are_clusters(expert_dataset):
    bank = EpisodeBank.from_folder(expert_dataset)
    # Chunk first (t uniform over the episode), then the goal after it along the leader's future. The old
    # goal-first draw (t_g uniform, then t uniform before it) had E[t / T] = 1/4 and mostly near goals.
    cfg = SampleConfig(augment=False, shuffle_robots=False, final_goal_prob=0.0, condition_prob=0.0)
    frac = []
    for k in range(300):
        i = k % len(bank)
        s = make_sample(bank, i, np.random.default_rng(k), cfg)
        P, lead = bank.positions(i), int(bank.leader[i])
        t = int(np.flatnonzero(np.abs(P[:, lead] - s["start"][lead]).max(axis=1) == 0)[0])
        later = np.flatnonzero(np.abs(P[t + 1:, lead] - s["goal"]).max(axis=1) == 0)
        assert len(later) or np.allclose(P[t, lead], s["goal"]), "the goal lies on the leader's path after t"
        frac.append(t / bank.num_steps[i])
    assert 0.4 < np.mean(frac) < 0.6
    sub = SampleConfig(subteam_prob=1.0, condition_prob=0.0)
    no_leader = 0
    for i in range(200):
        s = make_sample(bank, i % len(bank), np.random.default_rng(i), sub)
        n = int(s["num_robots"])
        assert 1 <= n <= 4 and n <= bank.num_robots[i % len(bank)]
        p = s["start"][:n]
        near = np.linalg.norm(p[:, None] - p[None], axis=-1) <= 15.0
        reach = near.copy()
        for _ in range(n):
            reach = (reach.astype(int) @ near.astype(int)) > 0
        assert reach.all(), "a cluster is connected"
        if s["goal_mask"].sum() == 0:
            no_leader += 1
            assert s["traj_mask"][:n].sum() >= 1 and s["traj_mask"][:n].sum() < n and not s["map"][2].any()
    assert 20 < no_leader < 120  # a cluster rooted at a follower often grows to hold the leader


def test_shard_runs_equal_one_run_byte_for_byte(tmp_path):
    sets = ["--set", "dataset.maps_per_unit=2", "--set", "dataset.team_sizes={2: 1, 3: 1}"]
    common = ["--maps", "train", "--num-maps", "6", "--episodes-per-map", "2", "--workers", "0", *sets]
    assert cli("generate.py", *common, "--out", str(tmp_path / "one")).returncode == 0
    for k in range(2):
        r = cli("generate.py", *common, "--out", str(tmp_path / "two"), "--shard", f"{k}/2")
        assert r.returncode == 0, r.stderr
    files = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*.parquet"))
    assert len(files) == 6
    for f in files:
        assert (tmp_path / "one" / f).read_bytes() == (tmp_path / "two" / f).read_bytes(), f
    assert json.loads((tmp_path / "two" / "manifest.json").read_text())["status"] == "complete"
    r = subprocess.run([sys.executable, "-m", "roken", "validate", str(tmp_path / "two")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0 and "complete" in r.stdout


@pytest.mark.parametrize("recipe", sorted(p.name for p in (ROOT / "configs" / "pretrain").glob("*.yaml")))
def test_recipes_load_and_are_consistent(recipe):
    cfg = load_config(ROOT / "configs" / "pretrain" / recipe)
    ckpt.cross_check(cfg.model, cfg.samples, cfg.task.max_step, recipe)
    assert cfg.train.batch_size in (32, 128) and cfg.train.lr == 5e-4
    if recipe.startswith("four"):
        assert cfg.samples.team_size_weights == {4: 1.0}
    assert (cfg.samples.subteam_prob > 0) == (recipe == "four-masked.yaml")


@pytest.mark.parametrize("variants", sorted(p.name for p in (ROOT / "configs" / "ablate").glob("*.yaml")))
def test_ablation_files_are_valid_over_the_cpu_recipe(variants):
    """Every variant of a shipped ablation file, over the recipe its command names, passes the checks a run makes
    and builds its model."""
    from roken.model.dit import RokenDiT
    from roken.train.ablation import load_variants
    from roken.train.loop import check_sections
    for v in load_variants(ROOT / "configs" / "ablate" / variants):
        cfg = load_config(ROOT / "configs" / "pretrain" / "cpu.yaml", v["overrides"])
        check_sections(cfg)
        RokenDiT(cfg.model)


@pytest.mark.parametrize("name", ["roken-small-mixed", "roken-cpu-four", "roken-cpu-four-masked"])
def test_the_shipped_model_loads_and_plans(name):
    shipped = ROOT / "models" / name
    loaded = ckpt.load(shipped, task_max_step=0.5)
    assert (shipped / "MODEL_CARD.md").is_file() and (shipped / "model.safetensors").stat().st_size < 10e6
    from roken.model.diffusion import COND_KEYS, ddim_sample, make_prompt
    from roken.data.samples import sample_shapes

    cfg = load_config(None, [])
    occ = np.zeros((140, 140), np.float32)
    occ[:, :20] = 1
    sample = {k: np.zeros(shape, dtype) for k, (shape, dtype) in sample_shapes(cfg.samples).items()}
    sample["start"][:4] = [[60, 60], [66, 60], [60, 66], [66, 66]]
    sample["robot_mask"][:4] = True
    sample["goal_mask"][0] = 1
    sample["rel_goal"][0] = np.array([60.0, 0.0]) / 70.0
    sample["map"][0] = occ
    batch = collate([sample])
    cond = {k: batch[k] for k in COND_KEYS + ("map",)}
    chunk = ddim_sample(loaded.model, loaded.schedule, make_prompt(loaded.model, cond, num_candidates=4), steps=10).chunk
    assert chunk.shape == (4, 10, 16, 2) and torch.isfinite(chunk).all()
    assert float(chunk[:, 0, :, 0].sum(-1).mean()) > 0, "the leader heads toward its goal (+x)"
