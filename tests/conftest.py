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
