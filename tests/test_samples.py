"""Training samples: chunk encoding, goals, waypoints, local occupancy, augmentation, padding, masks."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from roken.data import shards
from roken.data.loader import ChunkDataset, EpisodeBatchToSamples, collate
from roken.data.samples import (EpisodeBank, SampleConfig, decode_chunk, local_patches, make_sample,
                                transform_grid, transform_points)
from roken.world.geometry import clearance, pad_for_clearance

PLAIN = SampleConfig(augment=False, shuffle_robots=False, condition_prob=0.0, final_goal_prob=1.0)


@pytest.fixture(scope="module")
def bank(expert_dataset):
    return EpisodeBank.from_folder(expert_dataset)


def test_sample_shapes_padding_and_masks(bank):
    s = ChunkDataset(bank, SampleConfig())[0]
    N = int(s["num_robots"])
    assert s["chunk"].shape == (10, 16, 2) and s["map"].shape == (3, 140, 140) and s["sdf"].shape == (140, 140)
    assert s["waypoints"].shape == (10, 5, 2) and s["occ_small"].shape == s["occ_large"].shape == (10, 7, 7)
    assert s["robot_mask"].sum() == N and s["robot_mask"][:N].all()
    for key in ("chunk", "start", "rel_goal", "goal_mask", "traj_mask", "waypoints", "occ_small"):
        assert not s[key][N:].any(), f"padding of {key} must be zero"
    assert s["goal_mask"].sum() == 1 and s["traj_mask"].sum() < N
    # A chunk move spans 4 expert steps of at most 0.5 m each, and is normalised by 2 m.
    assert np.linalg.norm(s["chunk"][:N], axis=-1).max() <= 1.0 + 1e-5
    np.testing.assert_array_equal(s["map"][0] > 0.5, s["sdf"] < 0)  # occupancy channel vs SDF sign


def test_chunk_decodes_to_the_expert_positions_at_the_sampling_interval(bank):
    for i in range(len(bank)):
        rng = np.random.default_rng(i)
        s = make_sample(bank, i, rng, PLAIN)
        P, N = bank.positions(i), int(s["num_robots"])
        # Some t with P[t] == start must give every chunk point as P[t + 4 (k + 1)] (the end held after T).
        got = decode_chunk(s["chunk"][:N], s["start"][:N], PLAIN)
        ts = np.flatnonzero(np.abs(P - s["start"][:N]).max(axis=(1, 2)) == 0)
        idx = [np.minimum(t + 4 * np.arange(1, 17), len(P) - 1) for t in ts]
        assert any(np.allclose(got, P[ix].transpose(1, 0, 2), atol=1e-4) for ix in idx)
        absolute = make_sample(bank, i, np.random.default_rng(i), replace(PLAIN, representation="absolute"))
        np.testing.assert_allclose(decode_chunk(absolute["chunk"][:N], None, replace(PLAIN, representation="absolute")),
                                   got, atol=1e-4)
        assert np.abs(absolute["chunk"][:N]).max() <= 1.0


def test_goal_is_sampled_along_the_leaders_future_and_waypoints_follow_the_path(bank):
    cfg = replace(PLAIN, final_goal_prob=0.0)
    i = int(np.argmax(bank.num_steps))
    P = bank.positions(i)
    leader = int(bank.leader[i])
    for seed in range(20):
        s = make_sample(bank, i, np.random.default_rng(seed), cfg)
        j = int(np.flatnonzero(s["goal_mask"])[0])
        assert j == leader
        on_path = np.abs(P[:, leader] - s["goal"]).max(axis=1).min()
        assert on_path < 1e-5, "the goal must be a point of the leader's trajectory"
        np.testing.assert_allclose(s["rel_goal"][j] * 70.0, s["goal"] - s["start"][j], atol=1e-4)
        wps = s["start"][:, None] + s["waypoints"] * 40.0
        # Consecutive waypoints are at most 8 m apart (arc length 8 m), and the last ones sit at the goal once
        # the leader's remaining path is shorter than 40 m.
        steps = np.linalg.norm(np.diff(np.concatenate([s["start"][:, None], wps], axis=1), axis=1), axis=-1)
        assert steps[: int(s["num_robots"])].max() <= 8.0 + 1e-3
        t = int(np.flatnonzero(np.abs(P[:, leader] - s["start"][j]).max(axis=1) == 0)[0])
        t_g = int(np.flatnonzero(np.abs(P[:, leader] - s["goal"]).max(axis=1) == 0)[0])
        remaining = np.linalg.norm(np.diff(P[t:t_g + 1, leader], axis=0), axis=1).sum()
        if remaining < 40.0:
            np.testing.assert_allclose(wps[j, -1], s["goal"], atol=1e-4)


def test_local_patches_small_and_max_pooled_large():
    occ = np.zeros((30, 30), np.uint8)
    occ[10, 12] = 1  # one obstacle cell
    small, large = local_patches(occ, np.array([[12.5, 10.5], [1.2, 1.7]]), 7, 3)
    assert small[0, 3, 3] == 1 and small[0].sum() == 1  # centred on the robot's cell
    assert large[0, 3, 3] == 1 and large[0].sum() == 1  # the obstacle falls in the central 3 x 3 block
    # Near the corner, cells outside the map are obstacles: rows/cols -2..-1 in the small patch.
    assert small[1, :2].all() and small[1, :, :2].all() and small[1, 2:, 2:].sum() == 0


@pytest.mark.parametrize("element", range(8))
def test_dihedral_transform_maps_points_and_cells_consistently(element):
    rng = np.random.default_rng(element)
    occ = (rng.random((140, 140)) < 0.3).astype(np.uint8)
    pts = rng.uniform(0, 140, size=(500, 2))
    new_occ, new_pts = transform_grid(occ, element), transform_points(pts, element, 140)
    before = occ[np.floor(pts[:, 1]).astype(int), np.floor(pts[:, 0]).astype(int)]
    after = new_occ[np.floor(new_pts[:, 1]).astype(int), np.floor(new_pts[:, 0]).astype(int)]
    np.testing.assert_array_equal(before, after)


def test_rotation_augmentation_keeps_trajectories_collision_free(bank):
    """Every augmented sample's chunk, decoded on the sample's own (transformed) map, keeps the expert's
    clearance of at least d_obs_min = 1 m, and the transforms themselves preserve clearance exactly."""
    cfg = SampleConfig(condition_prob=0.0)
    seen = set()
    for k in range(64):
        i = k % len(bank)
        rng = np.random.default_rng(k)
        s = make_sample(bank, i, rng, cfg)
        N = int(s["num_robots"])
        pts = decode_chunk(s["chunk"][:N], s["start"][:N], cfg).reshape(-1, 2)
        padded = pad_for_clearance((s["map"][0] > 0.5).astype(np.uint8))
        assert clearance(padded, np.concatenate([pts, s["start"][:N]])).min() >= 1.0 - 1e-4
        seen.add(tuple(np.round(s["map"][0][:3, :3].ravel())))
    P = bank.positions(0).reshape(-1, 2)
    occ = bank.occupancy[int(bank.map_index[0])]
    base = clearance(pad_for_clearance(occ), P)
    for e in range(8):
        got = clearance(pad_for_clearance(transform_grid(occ, e)), transform_points(P, e, 140))
        np.testing.assert_allclose(got, base, atol=1e-5)


def test_heatmaps_peak_at_starts_and_goal(bank):
    s = make_sample(bank, 0, np.random.default_rng(0), PLAIN)
    N = int(s["num_robots"])
    cells = np.floor(s["start"][:N]).astype(int)
    assert (s["map"][1][cells[:, 1], cells[:, 0]] > 0.8).all()
    g = np.floor(s["goal"]).astype(int)
    assert s["map"][2][g[1], g[0]] > 0.8 and s["map"][2].max() <= 1.0


def test_masked_training_and_team_size_mixing(bank):
    cfg = SampleConfig(condition_prob=0.5, team_size_weights={2: 1.0, 6: 1.0})
    ds = ChunkDataset(bank, cfg, samples_per_epoch=400)
    batch = collate([ds[k] for k in range(400)])
    sizes = batch["num_robots"].numpy()
    assert set(sizes.tolist()) == {2, 6} and 0.4 < (sizes == 2).mean() < 0.6
    conditioned = batch["traj_mask"].sum(1).numpy()
    assert 0.4 < (conditioned > 0).mean() < 0.6
    assert (conditioned < sizes).all(), "at least one robot is always generated"
    assert batch["robot_mask"].dtype == torch.bool and batch["chunk"].dtype == torch.float32
    # Same (seed, epoch, index): the same sample; another epoch: another one.
    np.testing.assert_array_equal(ds[7]["chunk"], ds[7]["chunk"])
    ds.set_epoch(1)
    assert not np.array_equal(ChunkDataset(bank, cfg, samples_per_epoch=400)[7]["chunk"], ds[7]["chunk"])


def test_ray_style_batches_match_and_skip_failed_episodes(expert_dataset):
    table = shards.read_table(expert_dataset, "episodes")
    batch = {c: table.column(c).to_numpy(zero_copy_only=False) for c in table.column_names}
    batch["success"] = batch["success"].copy()
    batch["success"][0] = False
    out = EpisodeBatchToSamples(expert_dataset, SampleConfig(), samples_per_episode=2)(batch)
    assert out["chunk"].shape == (2 * (table.num_rows - 1), 10, 16, 2)
    again = EpisodeBatchToSamples(expert_dataset, SampleConfig(), samples_per_episode=2)(
        {k: v[1:] for k, v in batch.items()})
    for key in out:
        np.testing.assert_array_equal(out[key], again[key])  # keyed by episode id, not by batch position
    none = EpisodeBatchToSamples(expert_dataset, SampleConfig())({k: v[:1] for k, v in batch.items()})
    assert none["chunk"].shape == (0, 10, 16, 2)


def test_too_many_robots_names_the_fix(bank):
    with pytest.raises(ValueError, match="max_robots"):
        make_sample(bank, int(np.argmax(bank.num_robots)), np.random.default_rng(0), replace(PLAIN, max_robots=1))


def test_early_times_are_drawn_in_the_first_steps_when_asked(bank):
    cfg = replace(PLAIN, early_prob=1.0, early_steps=5)
    for i in range(len(bank)):
        s = make_sample(bank, i, np.random.default_rng(i), cfg)
        P, N = bank.positions(i), int(s["num_robots"])
        ts = np.flatnonzero(np.abs(P - s["start"][:N]).max(axis=(1, 2)) == 0)
        assert ts.min() < 5, "t is one of the first early_steps steps"
    with pytest.raises(ValueError, match="samples.early_prob"):
        from roken.data.samples import check
        check(replace(PLAIN, early_prob=1.5))
    # off (the default) draws exactly as before: the same sample for the same generator
    a = make_sample(bank, 0, np.random.default_rng(3), PLAIN)
    b = make_sample(bank, 0, np.random.default_rng(3), replace(PLAIN, early_steps=7))
    assert all(np.array_equal(a[k], b[k]) for k in a)
