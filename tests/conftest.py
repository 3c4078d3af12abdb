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
