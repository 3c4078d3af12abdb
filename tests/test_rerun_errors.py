"""What a new user hit in training, planning and post-training (issue 19): re-running finished runs, checkpoint and
model-config errors up front, divergence, exporting into the source, evaluation data as training data, and the
README's two set-up lines. Each feeds the input and checks the exit code, the message and what was written."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import cli

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "roken-small-mixed"
TINY = ["--preset", "tiny", "--batch-size", "4", "--set", "train.loader_workers=0", "--set", "train.val_fraction=0.34",
        "--set", "train.val_prompts=2", "--set", "train.closed_loop_every=0", "--set", "train.log_every=1",
        "--workers", "0"]


def run(script, *args):
    return cli(script, *args)


def test_readme_has_the_two_setup_commands_and_ci_runs_the_first():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert lines[0] == 'pip install torch==2.13.0 -e ".[test]" && python -m pytest -q'
    assert lines[1] == "pip install torch==2.13.0 -e . && roken quickstart --out runs/quickstart"
    assert 'bash -c "$(sed -n 1p README.md)"' in (ROOT / ".ci" / "run").read_text()


def test_rerun_of_a_finished_pretraining_prints_its_summary(expert_dataset, tmp_path):
    out = tmp_path / "run"
    args = ["--data", expert_dataset, "--out", str(out), "--steps", "2", *TINY]
    assert run("pretrain.py", *args).returncode == 0
    before = (out / "summary.json").read_text()
    r = run("pretrain.py", *args)
    assert r.returncode == 0 and "is finished" in r.stderr and "checkpoint:" in r.stdout, r.stderr[-2000:]
    assert (out / "summary.json").read_text() == before


@pytest.mark.parametrize("sets,message", [
    (["--set", "model.width=90"], "model.width=90 is not divisible by model.heads=4"),
    (["--set", "diffusion.prediction=x"], "diffusion.prediction must be one of eps, v, x0, got 'x'"),
    (["--set", "train.lr=1e12", "--set", "train.warmup_steps=0", "--set", "train.grad_clip=0"], "training diverged"),
])
def test_model_config_and_divergence_errors_are_one_line(expert_dataset, tmp_path, sets, message):
    out = tmp_path / "run"
    r = run("pretrain.py", "--data", expert_dataset, "--out", str(out), "--steps", "6", *TINY, *sets)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, r.stderr[-2000:]
    if "train.lr" not in " ".join(sets):
        assert not out.exists()


def test_a_run_starting_from_a_checkpoint_of_another_parametrisation_is_refused(expert_dataset, tmp_path):
    # a v-prediction model's output read as the noise would be a silent, wrong model (diffusion.prediction)
    assert run("pretrain.py", "--data", expert_dataset, "--out", str(tmp_path / "v"), "--steps", "2", *TINY,
               "--set", "diffusion.prediction=v").returncode == 0
    r = run("pretrain.py", "--data", expert_dataset, "--out", str(tmp_path / "eps"), "--steps", "2", *TINY,
            "--init", str(tmp_path / "v"))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert "diffusion.prediction: v -> eps" in r.stderr and "--set diffusion.prediction=v" in r.stderr
    assert not (tmp_path / "eps").exists()
    assert run("pretrain.py", "--data", expert_dataset, "--out", str(tmp_path / "v2"), "--steps", "2", *TINY,
               "--init", str(tmp_path / "v"), "--set", "diffusion.prediction=v").returncode == 0


def test_an_evaluation_folder_is_refused_as_training_data(tmp_path):
    ev = tmp_path / "ev"
    assert run("evaluate.py", "--robots", "2", "--episodes", "2", "--num-maps", "2", "--workers", "0",
               "--out", str(ev)).returncode == 0
    r = run("pretrain.py", "--data", str(ev), "--out", str(tmp_path / "run"), *TINY)
    assert r.returncode == 2 and "evaluation folder" in r.stderr and not (tmp_path / "run").exists()


@pytest.mark.parametrize("case", ["truncated", "replan"])
def test_checkpoint_errors_come_before_anything_is_written(tmp_path, case):
    ck = SHIPPED
    extra = []
    if case == "truncated":
        ck = tmp_path / "ck"
        shutil.copytree(SHIPPED, ck)
        w = ck / "model.safetensors"
        w.write_bytes(w.read_bytes()[:1000])
    else:
        extra = ["--replan-every", "17"]
    r = run("evaluate.py", "--planner", "roken", "--checkpoint", str(ck), "--robots", "2", "--episodes", "2",
            "--num-maps", "2", "--workers", "0", "--out", str(tmp_path / "ev"), *extra)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert ("safetensors" in r.stderr) if case == "truncated" else ("--replan-every 17" in r.stderr)
    assert not (tmp_path / "ev").exists()


def test_export_into_itself_is_refused_and_cards_keep_their_sections(tmp_path):
    r = cli("roken", "export", str(SHIPPED), str(SHIPPED))
    assert r.returncode == 2 and "is the source" in r.stderr
    out = tmp_path / "copy"
    r = cli("roken", "export", str(SHIPPED), str(out))
    assert r.returncode == 0, r.stderr
    old = [x for x in (SHIPPED / "MODEL_CARD.md").read_text().splitlines() if x.startswith("## ")]
    new = (out / "MODEL_CARD.md").read_text()
    assert all(h in new for h in old)


def test_quickstart_refuses_a_folder_it_did_not_make(tmp_path):
    (tmp_path / "report.md").write_text("mine")
    r = subprocess.run([sys.executable, "-m", "roken", "quickstart", "--out", str(tmp_path), "--workers", "0"],
                       capture_output=True, text=True, timeout=120)  # `roken quickstart` runs the script in a process
    assert r.returncode == 2 and "did not make" in r.stderr
    assert (tmp_path / "report.md").read_text() == "mine"


def test_another_checkpoint_is_refused_in_an_evaluation_folder(tmp_path):
    """Item 3: a second --checkpoint into the same --out names the fingerprints and writes nothing."""
    ev = tmp_path / "ev"
    base = ["--planner", "roken", "--robots", "2", "--episodes", "1", "--num-maps", "1", "--steps", "2",
            "--workers", "0", "--out", str(ev)]
    assert run("evaluate.py", *base, "--checkpoint", str(SHIPPED)).returncode == 0
    before = (ev / "episodes" / "roken-n02.parquet").read_bytes()
    r = run("evaluate.py", *base, "--checkpoint", str(ROOT / "models" / "roken-cpu-four"))
    assert r.returncode == 2 and "checkpoint: sha256" in r.stderr and "--overwrite" in r.stderr, r.stderr[-2000:]
    assert "Traceback" not in r.stderr and (ev / "episodes" / "roken-n02.parquet").read_bytes() == before


def _interrupt(cmd: list[str], ready, timeout: float = 240) -> subprocess.CompletedProcess:
    """Start `cmd`, send SIGINT (Ctrl-C) once `ready()` holds, return the finished process."""
    import signal
    import time

    # A shell's background job inherits SIGINT ignored, and Python then installs no KeyboardInterrupt handler:
    # the child gets the default disposition back, as a terminal's foreground job has it.
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    while not ready() and p.poll() is None and time.time() - t0 < timeout:
        time.sleep(0.2)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


def test_ctrl_c_in_pretraining_says_where_it_stopped_and_how_to_resume(expert_dataset, tmp_path):
    """Item 6: exit 130, the step, the kept checkpoint and the resume hint, no traceback."""
    out = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "pipelines" / "pretrain.py"), "--data", expert_dataset, "--out", str(out),
           "--steps", "100000", *TINY, "--set", "train.checkpoint_every=2"]
    r = _interrupt(cmd, lambda: any(out.glob("checkpoint-*/config.json")))
    assert r.returncode == 130, r.stderr[-2000:]
    assert "interrupted at step" in r.stderr and "checkpoint at step" in r.stderr
    assert "re-run the same command to resume" in r.stderr and "Traceback" not in r.stderr


def test_posttraining_ctrl_c_and_a_finished_rerun_keep_the_summary(expert_dataset, tmp_path):
    """Items 6 and 7 for posttrain.py: Ctrl-C exits 130 with the resume hint; re-running a finished run keeps
    summary.json byte for byte and prints it."""
    out = tmp_path / "grpo"
    small = ["--set", "rl.group_size=2", "--set", "rl.prompts_per_iteration=2", "--set", "rl.train_transitions=2",
             "--set", "rl.minibatch_prompts=2", "--set", "rl.checkpoint_every=1", "--set", "rl.min_future=32",
             "--set", "plan.steps=2", "--workers", "0"]
    cmd = [sys.executable, str(ROOT / "pipelines" / "posttrain.py"), "--checkpoint", str(SHIPPED), "--data",
           expert_dataset, "--out", str(out), *small]
    r = _interrupt(cmd + ["--iterations", "1000"], lambda: any(out.glob("checkpoint-*/config.json")))
    assert r.returncode == 130 and "re-run the same command to resume" in r.stderr, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    done = cli("posttrain.py", *cmd[2:], "--iterations", "2")
    assert done.returncode == 0, done.stderr[-2000:]
    before = (out / "summary.json").read_bytes()
    again = cli("posttrain.py", *cmd[2:], "--iterations", "2")
    assert again.returncode == 0 and "checkpoint:" in again.stdout, again.stderr[-2000:]
    assert (out / "summary.json").read_bytes() == before


def test_a_corrupt_shard_is_named_with_the_fix(expert_dataset, tmp_path):
    """Item 11: the unreadable shard and that re-running generate.py repairs it; nothing written."""
    ds = tmp_path / "ds"
    shutil.copytree(expert_dataset, ds)
    shard = sorted((ds / "episodes").glob("*.parquet"))[0]
    shard.write_bytes(shard.read_bytes()[:300])
    r = run("pretrain.py", "--data", str(ds), "--out", str(tmp_path / "run"), *TINY)
    assert r.returncode == 2 and shard.name in r.stderr and "Re-run the pipelines/generate.py" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "run").exists()
