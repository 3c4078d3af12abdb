import numpy as np
import pytest

from roken.world.maps import MapConfig
from roken.world.tasks import TaskConfig


@pytest.fixture
def mc():
    return MapConfig()


@pytest.fixture
def tc():
    return TaskConfig()


@pytest.fixture(scope="module")
def tiny():
    """A random tiny Roken planner: it moves robots anywhere, which is what the execution, mask and driver tests
    need (AdaLN-Zero starts at eps = 0, so the final layer is drawn at random to make the output non-trivial)."""
    import torch

    from roken.data.samples import SampleConfig
    from roken.model.diffusion import DiffusionConfig, NoiseSchedule
    from roken.model.dit import RokenDiT, preset
    from roken.plan import RokenPlanner

    torch.manual_seed(0)
    model = RokenDiT(preset("tiny"))
    for p in model.final.parameters():
        torch.nn.init.normal_(p, std=0.5)
    return RokenPlanner(model, NoiseSchedule(DiffusionConfig(num_steps=20)), SampleConfig(), "cpu")


def open_map(size=60, canvas=None):
    """A free square with an obstacle border (1 cell)."""
    occ = np.zeros((size, size), np.uint8)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = 1
    return occ


def free_ports(n: int) -> list[int]:
    """n distinct TCP ports free on 127.0.0.1 right now."""
    import socket

    socks = []
    for _ in range(n):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def short_tmpdir(prefix: str) -> str:
    """A short temp dir: Ray puts Unix sockets under its temp dir, and socket paths are limited to 107 bytes."""
    import tempfile

    return tempfile.mkdtemp(prefix=prefix, dir="/tmp")


@pytest.fixture
def ray_tmp():
    """A short, private RAY_TMPDIR for a test's local cluster, removed afterwards."""
    import shutil

    d = short_tmpdir("rk")
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture(scope="session")
def expert_dataset(tmp_path_factory):
    """A small real expert dataset (6 maps x 4 episodes, mixed team sizes) made in-process, for the sample
    and model tests."""
    from roken.config import load_config
    from roken.data.build import build_dataset
    from roken.units import InProcessRunner

    out = tmp_path_factory.mktemp("expert") / "ds"
    cfg = load_config(None, ["dataset.num_maps=6", "dataset.episodes_per_map=4", "dataset.maps_per_unit=6",
                             "dataset.team_sizes={2: 1, 3: 1, 4: 2, 6: 1}", "dataset.seed=3"])
    build_dataset(cfg, str(out), InProcessRunner())
    return str(out)


_PIPELINES: dict = {}


def load_pipeline(name: str):
    """pipelines/NAME.py as a module (loaded once per test session; the pipelines import `common` beside them)."""
    import importlib.util
    import sys
    from pathlib import Path

    if name not in _PIPELINES:
        folder = Path(__file__).resolve().parents[1] / "pipelines"
        if str(folder) not in sys.path:
            sys.path.insert(0, str(folder))
        spec = importlib.util.spec_from_file_location(f"pipeline_{name}", folder / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        _PIPELINES[name] = mod
    return _PIPELINES[name]


def cli(target: str, *args: str):
    """Run `python pipelines/TARGET ARGS` (target "evaluate.py") or `python -m roken ARGS` (target "roken") in this
    process and return what subprocess.run would: the same main(argv) the script's __main__ calls, with stdout
    and stderr captured and an argparse exit turned into its code. A fresh interpreter spends 3-5 s importing
    torch and Ray before the first line of a 0.5 s error path; that was most of the suite's subprocess time. Use
    it for --workers 0 runs only: Ray workers, Ctrl-C and killed processes need a process of their own."""
    import contextlib
    import io
    import subprocess

    if target == "roken":
        from roken.cli import main
    else:
        main = load_pipeline(target.removesuffix(".py")).main
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as e:  # argparse's usage errors, and sys.exit inside a command
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    return subprocess.CompletedProcess([target, *args], code or 0, out.getvalue(), err.getvalue())


def in_process(cmd: list[str]):
    """cli() for a command line written for subprocess: [python, .../pipelines/NAME.py, ...] or
    [python, -m, roken, ...]."""
    if cmd[1:3] == ["-m", "roken"]:
        return cli("roken", *cmd[3:])
    assert cmd[1].endswith(".py") and "pipelines" in cmd[1], cmd[:2]
    return cli(cmd[1].rsplit("/", 1)[-1], *cmd[2:])
