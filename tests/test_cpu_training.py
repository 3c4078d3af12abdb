"""The CPU training levers: K noise draws per encoded sample, the SDF modes, the laptop encoder and ego crops,
closed-loop validation on the `val` split picking "best", and the ablation command with resume."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from roken.config import load_config
from roken.data.loader import collate
from roken.data.samples import EpisodeBank, make_sample
from roken.model.diffusion import NoiseSchedule
from roken.model.dit import RokenDiT, local_crops
from roken.model.losses import SDF_MODES, pretraining_loss
from roken.train import checkpoint as ckpt
from roken.train.loop import Pretraining, PretrainSpec
from roken.world.maps import MapConfig, generate_map

ROOT = Path(__file__).resolve().parents[1]
TINY = ["model.width=64", "model.depth=2", "model.heads=4", "model.mlp_hidden=128", "model.map_channels=16",
        "model.map_blocks=1", "train.batch_size=4", "train.loader_workers=0", "train.val_fraction=0.34",
        "train.val_prompts=4", "train.log_every=1", "train.warmup_steps=2", "train.closed_loop_tasks=3",
        "plan.batch_size=8"]


def batch_of(dataset, n, cfg, seed=0):
    bank = EpisodeBank.from_folder(dataset)
    import numpy as np
    return collate([make_sample(bank, i % len(bank), np.random.default_rng([seed, i]), cfg) for i in range(n)])


@pytest.mark.parametrize("extra", [[], ["model.map_encoder=patch", "model.local_crop=5"]])
def test_k_draws_equal_k_separate_batches(expert_dataset, extra):
    cfg = load_config(None, TINY + extra + ["loss.sdf_mode=stopgrad", "loss.sdf_wp=0"])  # trajectory part: per draw
    torch.manual_seed(0)
    model = RokenDiT(cfg.model).eval()
    sched = NoiseSchedule(cfg.diffusion)
    b = batch_of(expert_dataset, 3, cfg.samples)
    K = 4
    g = torch.Generator().manual_seed(1)
    k = torch.randint(0, sched.K, (3 * K,), generator=g)
    eps = torch.randn((3 * K,) + tuple(b["chunk"].shape[1:]), generator=g)
    loss_k, logs_k = pretraining_loss(model, sched, b, cfg.loss, cfg.samples, draws=K, k=k, eps=eps)
    # the same draws as K separate batches of the same samples (each row with its own map copy)
    rep = {key: v.repeat_interleave(K, 0) for key, v in b.items()}
    loss_1, logs_1 = pretraining_loss(model, sched, rep, cfg.loss, cfg.samples, draws=1, k=k, eps=eps)
    assert torch.allclose(logs_k["losses/traj"], logs_1["losses/traj"], atol=1e-5)
    assert torch.allclose(logs_k["losses/sdf"], logs_1["losses/sdf"], atol=1e-5)
    # auxiliary terms once per sample: the first draw of each sample
    first = {key: v[::K] for key, v in rep.items()}
    _, logs_a = pretraining_loss(model, sched, first, cfg.loss, cfg.samples, k=k[::K], eps=eps[::K])
    assert torch.allclose(logs_k["losses/wp"], logs_a["losses/wp"], atol=1e-5)
    assert torch.allclose(logs_k["losses/occ"], logs_a["losses/occ"], atol=1e-5)


def test_sdf_modes_run_and_stopgrad_moves_only_its_own_move(expert_dataset):
    base = load_config(None, TINY)
    b = batch_of(expert_dataset, 2, base.samples)
    for mode in SDF_MODES:
        cfg = load_config(None, TINY + [f"loss.sdf_mode={mode}", "loss.wp=0", "loss.occ=0", "loss.traj=0"])
        torch.manual_seed(0)
        model = RokenDiT(cfg.model)
        loss, logs = pretraining_loss(model, NoiseSchedule(cfg.diffusion), b, cfg.loss, cfg.samples,
                                      generator=torch.Generator().manual_seed(0), draws=2)
        assert torch.isfinite(loss) and "losses/sdf" in logs
        loss.backward()
    # stopgrad: the penalty of point h reaches move h only. The paper's cumulative sum gives move h the sum of
    # points h..H-1, so paper[h] - paper[h+1] is point h's own gradient, which is what stopgrad gives move h.
    from roken.model.losses import _sdf_term
    ramp = torch.linspace(-2.0, 2.0, 140).expand(2, 140, 140).contiguous()  # every point within d_thres, sloped
    grads = {}
    for mode in ("paper", "stopgrad"):
        cfg = load_config(None, TINY + [f"loss.sdf_mode={mode}", "diffusion.clip_sample=0", "loss.sdf_wp=0"])
        sched = NoiseSchedule(cfg.diffusion)
        x0 = b["chunk"].clone()
        k = torch.zeros(2, dtype=torch.long)
        xk = sched.q_sample(x0, k, torch.zeros_like(x0))
        eps_hat = torch.zeros_like(x0, requires_grad=True)
        real = b["robot_mask"].float()
        one = torch.zeros_like(real)
        one[0, 0] = 1
        out = {"eps": eps_hat, "waypoints": b["waypoints"]}
        _sdf_term(sched, dict(b, sdf=ramp), cfg.loss, cfg.samples, out, x0, xk, k, torch.zeros_like(real), one,
                  1).backward()
        grads[mode] = eps_hat.grad[0, 0]  # (H, 2)
    own = torch.cat([grads["paper"][:-1] - grads["paper"][1:], grads["paper"][-1:]])
    assert grads["stopgrad"].abs().sum() > 0
    assert torch.allclose(grads["stopgrad"], own, atol=1e-6, rtol=1e-4)


def test_local_crops_read_the_occupancy_around_each_robot():
    occ = torch.zeros(1, 140, 140)
    occ[0, 50:60, 70:80] = 1  # rows 50..59, columns 70..79
    c = local_crops(occ, torch.tensor([[[75.5, 55.5], [10.5, 10.5], [0.5, 0.5]]]), 3)
    assert torch.allclose(c[0, 0, :9], torch.ones(9), atol=1e-4)  # inside the block
    assert torch.allclose(c[0, 1], torch.zeros(18), atol=1e-4)  # open space at both scales
    assert c[0, 2, 0] > 0.99 and c[0, 2, 4] < 1e-3  # outside the canvas is obstacle, the cell itself free


def test_val_split_is_disjoint_and_eval_datasets_are_refused(tmp_path, expert_dataset):
    mc = MapConfig()
    a, b, c = (generate_map(mc, s, 0).occupancy for s in ("train", "val", "eval"))
    assert (a != b).any() and (b != c).any() and (a != c).any()
    from roken.train.data import check_dataset
    import shutil
    bad = tmp_path / "evalds"
    shutil.copytree(expert_dataset, bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["config"]["dataset"]["maps"] = "eval"
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ValueError, match="eval.*test set.*--maps val"):
        check_dataset(str(bad), "--val-data")


def test_closed_loop_validation_writes_its_keys_and_picks_best(expert_dataset, tmp_path):
    spec = PretrainSpec.of(load_config(None, TINY + ["train.steps=4", "train.closed_loop_every=2", "train.eval_every=2",
                                                     "train.checkpoint_every=2", "train.keep_checkpoints=1"]))
    run = Pretraining(spec, expert_dataset, tmp_path)
    summary = run.fit()
    rows = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    cl = [r for r in rows if "closed_loop/success" in r]
    assert [r["step"] for r in cl] == [2, 4]
    keys = ("closed_loop/success", "closed_loop/reach", "closed_loop/obstacle_collision",
            "closed_loop/inter_collision", "closed_loop/connectivity", "val/first_move_cos_leader",
            "val/first_move_cos_follower", "val/l2_executed_m")
    assert all(k in summary["validation"] for k in keys)
    # "best" ranks by closed-loop success, then reach, and survives pruning
    import shutil

    def set_validation(d, success, reach, step=None):
        cfg = json.loads((d / "config.json").read_text())
        cfg["validation"] = {"closed_loop/success": success, "closed_loop/reach": reach}
        cfg["step"] = cfg["step"] if step is None else step
        (d / "config.json").write_text(json.dumps(cfg))
    newest = ckpt.list_checkpoints(tmp_path)[-1]
    set_validation(newest, 0.25, 0.5)
    other = tmp_path / "checkpoint-0000001"
    shutil.copytree(newest, other)
    for success, reach, best in ((0.5, 0.1, other), (0.25, 0.9, other), (0.25, 0.4, newest)):
        set_validation(other, success, reach, step=1)
        assert ckpt.find(tmp_path, "best") == best
    set_validation(other, 0.5, 0.1, step=1)
    ckpt.prune(tmp_path, 1)  # keeps the newest and the best
    assert other.is_dir() and newest.is_dir()


def test_ablation_writes_both_files_and_resume_skips_finished(expert_dataset, tmp_path):
    variants = tmp_path / "v.yaml"
    variants.write_text("variants:\n  - {name: a, set: []}\n  - {name: b, set: [train.noise_draws=2, loss.sdf_mode=off]}\n")
    cmd = [sys.executable, str(ROOT / "pipelines" / "ablate.py"), "--data", expert_dataset, "--out",
           str(tmp_path / "abl"), "--variants", str(variants), "--steps", "2", "--episodes", "2", "--workers", "0"]
    cmd += sum((["--set", s] for s in TINY if not s.startswith("train.closed_loop_tasks")), [])
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = json.loads((tmp_path / "abl" / "ablation.json").read_text())["variants"]
    keys = ("name", "overrides", "steps", "cpu_seconds", "success", "reach", "obstacle_collision", "inter_collision",
            "connectivity", "first_move_cos_follower")
    assert [x["name"] for x in rows] == ["a", "b"] and all(k in x for x in rows for k in keys)
    assert (tmp_path / "abl" / "ablation.md").read_text().count("\n| ") >= 3
    assert (tmp_path / "abl" / "ablation.png").stat().st_size > 0
    # interrupted: b's result is lost, a's is kept; the re-run trains b only
    (tmp_path / "abl" / "variants" / "b" / "result.json").unlink()
    before = (tmp_path / "abl" / "variants" / "a" / "result.json").read_text()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "1 finished earlier" in r.stderr, r.stderr[-2000:]
    assert (tmp_path / "abl" / "variants" / "a" / "result.json").read_text() == before


@pytest.mark.parametrize("bad, message", [("diffusion.prediction=q", "diffusion.prediction must be one of"),
                                          ("model.heads=5", "not divisible by model.heads=5"),
                                          ("train.schedule=step", "train.schedule must be")])
def test_ablation_refuses_a_bad_variant_before_any_trains(expert_dataset, tmp_path, bad, message):
    """A bad value in a later variant is named (file, variant, key) before the first variant spends its budget."""
    variants = tmp_path / "v.yaml"
    variants.write_text(f"variants:\n  - {{name: ok, set: []}}\n  - {{name: late, set: [{bad}]}}\n")
    r = subprocess.run([sys.executable, str(ROOT / "pipelines" / "ablate.py"), "--data", expert_dataset, "--out",
                        str(tmp_path / "abl"), "--variants", str(variants), "--steps", "2", "--workers", "0"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "variant 'late'" in r.stderr and message in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "abl").exists()


def test_separation_term_pushes_close_generated_robots_apart_and_spares_given_ones(expert_dataset):
    """loss.sep on a hand-made chunk: a close pair is penalised and pushed apart, given robots never move."""
    from roken.model.losses import _sep_term
    cfg = load_config(None, TINY + ["loss.sdf_mode=stopgrad", "diffusion.clip_sample=0", "loss.sep=1"])
    sched = NoiseSchedule(cfg.diffusion)
    H = batch_of(expert_dataset, 1, cfg.samples)["chunk"].shape[2]
    n = 4
    real = torch.ones(1, n)
    start = torch.tensor([[[50.0 + 20 * i, 50.0] for i in range(n)]])
    start[0, 1] = torch.tensor([51.0, 50.0])  # robots 0 and 1 start 1 m apart, the others 20 m from every robot
    b = {"start": start}
    x0 = torch.zeros(1, n, H, 2)  # every robot stays where it is
    k = torch.zeros(1, dtype=torch.long)
    xk = sched.q_sample(x0, k, torch.zeros_like(x0))

    def term(fixed):
        eps_hat = torch.zeros_like(x0, requires_grad=True)
        out = {"eps": eps_hat}
        val = _sep_term(sched, b, cfg.loss, cfg.samples, out, x0, xk, k, fixed, real - fixed, real, 1)
        val.backward()
        return val, eps_hat.grad[0]

    val, g = term(torch.zeros_like(real))
    assert val > 0
    # descending the penalty moves robot 0 toward -x and robot 1 toward +x (eps_hat enters x0_hat with a minus sign)
    step = -g
    assert (sched.predict_x0(xk, k, step[None]) - x0)[0, 0, :, 0].sum() < 0
    assert (sched.predict_x0(xk, k, step[None]) - x0)[0, 1, :, 0].sum() > 0
    assert g[2:].abs().sum() == 0  # robots far from every other get no push
    fixed = torch.zeros_like(real)
    fixed[0, 0] = 1  # robot 0 given: its pair still counts, but only robot 1 moves
    val1, g1 = term(fixed)
    assert val1 > 0 and g1[0].abs().sum() == 0 and g1[1].abs().sum() > 0
    fixed[0, 1] = 1  # both given: nothing to learn from that pair
    val2, _ = term(fixed)
    assert val2 == 0
    # a team whose every pair is beyond loss.sep_distance has no penalty at all
    b["start"][0, 1] = torch.tensor([55.0, 50.0])
    val3, g3 = term(torch.zeros_like(real))
    assert val3 == 0 and g3.abs().sum() == 0
