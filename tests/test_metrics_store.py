import numpy as np
import pyarrow.parquet as pq
import pytest

from roken.data.store import (StoreError, atomic_write_table, episodes_table, maps_table, read_episodes,
                              read_maps, read_run)
from roken.eval.metrics import episode_metrics, summarize
from roken.world.grid import GridMap


@pytest.fixture
def world():
    occ = np.zeros((40, 40), np.uint8)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = 1
    occ[18:22, 18:22] = 1  # a block in the middle
    return GridMap("hand", occ)


def straight(start, end, T):
    s = np.linspace(0, 1, T + 1)[:, None]
    return np.asarray(start) + (np.asarray(end) - np.asarray(start)) * s


def team(*trajs):
    return np.stack(trajs, axis=1)


GOAL = np.array([34.0, 5.0])


def test_success(world, tc):
    p = team(straight([5, 5], [34, 5], 60), straight([5, 9], [25, 9], 60))
    m = episode_metrics(p, world, GOAL, 0, tc)
    assert m.success and m.reach and m.connectivity and not m.obstacle_collision and not m.inter_collision
    assert np.isclose(m.astar_length, 29.0)
    assert np.isclose(m.path_length, (29 + 20) / 2)


def test_each_failure_kind(world, tc):
    # obstacle: the follower passes 0.5 m from the block (clearance < 1)
    p = team(straight([5, 5], [34, 5], 60), straight([5, 17.5], [30, 17.5], 60))
    m = episode_metrics(p, world, GOAL, 0, tc)
    assert m.obstacle_collision and not m.success and m.reach
    # inter-robot: the two robots come within 1.5 m
    p = team(straight([5, 5], [34, 5], 60), straight([5, 6.5], [34, 6.5], 60))
    m = episode_metrics(p, world, GOAL, 0, tc)
    assert m.inter_collision and not m.obstacle_collision and not m.success
    # disconnected: the follower stays behind, 29 m away at the end
    p = team(straight([5, 5], [34, 5], 60), straight([5, 9], [5, 9], 60))
    m = episode_metrics(p, world, GOAL, 0, tc)
    assert not m.connectivity and not m.success and m.reach
    # no reach: the leader stops 2 m short
    p = team(straight([5, 5], [32, 5], 60), straight([5, 9], [25, 9], 60))
    m = episode_metrics(p, world, GOAL, 0, tc)
    assert not m.reach and not m.success and m.connectivity
    # outside the map counts as an obstacle
    p = team(straight([5, 5], [34, 5], 60), straight([5, 9], [5, -3], 60))
    assert episode_metrics(p, world, GOAL, 0, tc).obstacle_collision


def test_summary_length_over_successes_only(world, tc):
    ok = episode_metrics(team(straight([5, 5], [34, 5], 60), straight([5, 9], [25, 9], 60)), world, GOAL, 0, tc)
    bad = episode_metrics(team(straight([5, 5], [32, 5], 60), straight([5, 9], [5, 9], 60)), world, GOAL, 0, tc)
    s = summarize([ok, bad])
    assert s["full_success"] == 0.5 and s["reach"] == 0.5 and s["episodes"] == 2
    assert np.isclose(s["length"], ok.path_length / ok.astar_length)


def _rows(world):
    p = team(straight([5, 5], [34, 5], 10), straight([5, 9], [25, 9], 10))
    return [{"episode_id": "e0", "map_id": world.map_id, "planner": "test", "num_robots": 2, "leader": 0,
             "num_steps": 10, "goal": GOAL, "positions": p, "success": True, "reach": True,
             "obstacle_collision": False, "inter_collision": False, "connectivity": True,
             "path_length": 1.0, "astar_length": 29.0, "seed": 0}]


def test_store_round_trip(tmp_path, world):
    atomic_write_table(maps_table([world]), tmp_path / "maps" / "m.parquet", "maps")
    atomic_write_table(episodes_table(_rows(world)), tmp_path / "episodes" / "e.parquet", "episodes")
    maps, eps = read_run(tmp_path)
    np.testing.assert_array_equal(maps["hand"].occupancy, world.occupancy)
    np.testing.assert_allclose(eps[0]["positions"], _rows(world)[0]["positions"], atol=1e-6)
    t = pq.read_table(tmp_path / "episodes" / "e.parquet")  # plain pyarrow / pandas read it too
    assert t.schema.metadata[b"schema_version"] == b"1"
    assert t.to_pandas().loc[0, "num_robots"] == 2
    assert not list(tmp_path.rglob("*.tmp"))  # no temporary file left behind


def test_corrupted_and_wrong_files(tmp_path, world):
    f = tmp_path / "e.parquet"
    atomic_write_table(episodes_table(_rows(world)), f, "episodes")
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(StoreError, match="e.parquet: not a readable Parquet"):
        read_episodes(f)
    bad = _rows(world)
    bad[0]["num_steps"] = 12  # positions no longer match
    atomic_write_table(episodes_table(bad), f, "episodes")
    with pytest.raises(StoreError, match="position values"):
        read_episodes(f)
    atomic_write_table(maps_table([world]), f, "maps")
    with pytest.raises(StoreError, match="expected 'episodes'"):
        read_episodes(f)
    assert read_maps(f)["hand"].shape == (40, 40)
