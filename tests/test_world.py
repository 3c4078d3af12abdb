from pathlib import Path

import numpy as np
import pytest

from roken.world.loaders import MapError, find_map_files, fit_to_canvas, load_map_file
from roken.world.maps import MapConfig, generate_map
from roken.world.tasks import TaskError, check_start, sample_task

MOVINGAI = Path(__file__).resolve().parents[2] / "shared" / "data" / "movingai"
needs_movingai = pytest.mark.skipif(not MOVINGAI.is_dir(), reason="shared/data/movingai not beside the checkout")


@needs_movingai
def test_every_movingai_map_loads(mc):
    files = find_map_files(str(MOVINGAI))
    assert len(files) >= 13
    for f in files:
        try:
            gm = load_map_file(f, mc)
        except MapError as e:  # only a map whose corridors are too narrow at canvas scale may be refused
            assert "3 x 3" in e.reason, e
            continue
        assert gm.shape == (140, 140)
        assert gm.occupancy[:1].all() or gm.occupancy.shape[0] == 140  # padded canvas
        assert gm.safe_cells.any()


@needs_movingai
def test_movingai_parsing_and_scaling(mc):
    gm = load_map_file(MOVINGAI / "maze-32-32-2.map", mc)
    assert gm.meta["scale"] == 4.0  # 32 -> 128, corridors of 2 become 8 cells wide
    raw = (MOVINGAI / "maze-32-32-2.map").read_text().splitlines()[4:]
    r, c = 5, 7
    expected = raw[r][c] in "@OTW"
    off = (140 - 128) // 2
    assert gm.occupancy[off + 4 * r: off + 4 * r + 4, off + 4 * c: off + 4 * c + 4].all() == expected
    big = load_map_file(MOVINGAI / "den312d.map", mc)
    assert big.meta["scale"] == 1.0


def test_fit_max_pools_large_maps():
    occ = np.zeros((300, 200), np.uint8)
    occ[101, 57] = 1  # a single obstacle cell must survive the down-scaling
    fitted, info = fit_to_canvas(occ, 140, 4)
    assert info["scale"] == 1 / 3
    assert fitted.shape == (140, 140)
    inner = fitted[20:120, (140 - 67) // 2:(140 - 67) // 2 + 67]
    assert inner[:, :66].sum() == 1 and inner[33, 19] == 1  # the cell survives, in its pooled block
    assert inner[:, 66].all()  # the last block column holds the (blocked) outside of the map


def test_png_and_npy_loaders(tmp_path, mc):
    from PIL import Image

    occ = np.zeros((40, 40), np.uint8)
    occ[10:20, 10:20] = 1
    img = np.where(occ == 1, 0, 255).astype(np.uint8)  # dark = obstacle
    Image.fromarray(img).save(tmp_path / "m.png")
    np.save(tmp_path / "m.npy", occ)
    a = load_map_file(tmp_path / "m.png", mc)
    b = load_map_file(tmp_path / "m.npy", mc)
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    assert a.meta["scale"] == 3.0


@pytest.mark.parametrize("name,content,needle", [
    ("cube.npy", np.zeros((4, 4, 4)), "2-D"),
    ("gray.npy", np.full((20, 20), 0.5), "non-binary"),
    ("blocked.npy", np.ones((20, 20)), "blocked"),
    ("narrow.npy", None, "3 x 3"),
    ("junk.png", b"not an image", "unreadable"),
    ("junk.map", "hello\nworld\n", "MovingAI"),
])
def test_bad_maps_have_clear_errors(tmp_path, mc, name, content, needle):
    path = tmp_path / name
    if name == "narrow.npy":
        content = np.ones((140, 140), np.uint8)
        content[70, 10:130] = 0  # a 1-cell corridor: no robot fits
    if isinstance(content, np.ndarray):
        np.save(path, content)
    elif isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(MapError) as e:
        load_map_file(path, mc)
    assert needle in str(e.value) and name in str(e.value)


def test_generated_maps_deterministic_and_splits_disjoint():
    mc = MapConfig(families={"blocks": 1, "rooms": 1, "maze": 1, "forest": 1})
    a = generate_map(mc, "train", 7)
    b = generate_map(mc, "train", 7)
    np.testing.assert_array_equal(a.occupancy, b.occupancy)
    train = {generate_map(mc, "train", i).occupancy.tobytes() for i in range(12)}
    evals = {generate_map(mc, "eval", i).occupancy.tobytes() for i in range(12)}
    assert not train & evals
    fams = {generate_map(mc, "eval", i).meta["family"] for i in range(24)}
    assert fams == {"blocks", "rooms", "maze", "forest"}


def test_paper_blocks_maps():
    mc = MapConfig()
    fr = []
    for i in range(20):
        gm = generate_map(mc, "eval", i)
        assert gm.shape == (140, 140)
        assert gm.occupancy[:20].all() and gm.occupancy[120:].all()  # 100 x 100 centred, padding blocked
        fr.append(gm.occupancy[20:120, 20:120].mean())
    assert 0.03 < min(fr) and max(fr) < 0.6


@pytest.mark.parametrize("n", [1, 2, 4, 10])
def test_tasks_are_valid(mc, tc, n):
    for i in range(5):
        gm = generate_map(mc, "eval", i)
        t = sample_task(gm, n, tc, np.random.default_rng([1, n, i]))
        assert check_start(gm, t.starts, tc) is None
        assert np.linalg.norm(t.starts[t.leader] - t.goal) >= tc.min_goal_distance
        assert gm.safe_graph.component[gm.safe_graph.node_of(t.goal)] == \
            gm.safe_graph.component[gm.safe_graph.node_of(t.starts[t.leader])]


def test_task_on_impossible_map_reports_reason(tc):
    from roken.world.grid import GridMap

    occ = np.ones((140, 140), np.uint8)
    occ[60:80, 60:80] = 0  # 20 x 20 room: no goal 50 m away
    with pytest.raises(TaskError, match="no goal >= 50 m"):
        sample_task(GridMap("room", occ), 4, tc, np.random.default_rng(0))
