import numpy as np

from roken.world.geometry import bilinear, clearance, line_of_sight, pad_for_clearance, signed_distance_field
from roken.world.paths import SQRT2, GridGraph, octile_length


def test_sdf_signs_and_values():
    occ = np.zeros((9, 9), np.uint8)
    occ[3:6, 3:6] = 1
    sdf = signed_distance_field(occ)
    assert sdf[4, 4] < 0 and sdf[3, 3] < 0  # inside the block
    assert np.isclose(sdf[4, 2], 0.5) and np.isclose(sdf[4, 1], 1.5)  # left of the block
    assert (sdf[occ == 0] > 0).all() and (sdf[occ == 1] < 0).all()
    assert np.isclose(sdf[4, 0], 0.5)  # the border outside the map is an obstacle


def test_bilinear_value_and_gradient():
    f = np.add.outer(np.arange(5.0) * 2.0, np.arange(6.0) * 3.0)  # f = 2 r + 3 c at centres
    pts = np.array([[2.2, 1.7], [3.9, 3.1]])
    val, grad = bilinear(f, pts, with_grad=True)
    np.testing.assert_allclose(val, 2 * (pts[:, 1] - 0.5) + 3 * (pts[:, 0] - 0.5))
    np.testing.assert_allclose(grad, [[3, 2], [3, 2]])


def test_clearance_exact():
    occ = np.zeros((10, 10), np.uint8)
    occ[5, 5] = 1  # unit square [5,6) x [5,6)
    pad = pad_for_clearance(occ)
    pts = np.array([[4.5, 5.5], [6.3, 5.5], [4.4, 4.4], [5.5, 5.5], [-0.1, 3.0], [0.5, 0.5]])
    c = clearance(pad, pts)
    np.testing.assert_allclose(c[:4], [0.5, 0.3, np.hypot(0.6, 0.6), 0.0])
    assert c[4] == 0.0  # outside the map
    assert np.isclose(c[5], 0.5)  # next to the outside


def test_octile_lengths_on_known_maps():
    free = np.ones((10, 10), bool)
    assert np.isclose(octile_length(free, np.array([0.5, 0.5]), np.array([9.5, 0.5])), 9.0)
    assert np.isclose(octile_length(free, np.array([0.5, 0.5]), np.array([9.5, 9.5])), 9 * SQRT2)
    assert np.isclose(octile_length(free, np.array([0.5, 0.5]), np.array([9.5, 3.5])), 6 + 3 * SQRT2)
    # a wall with one gap forces a detour; no corner cutting through the gap's corners
    free = np.ones((5, 5), bool)
    free[:4, 2] = False  # wall in column 2, gap at row 4
    g = GridGraph.build(free)
    d = g.field_grid(g.node_of(np.array([0.5, 0.5])))
    # to the gap cell (4, 2): (0,0) diag (1,1), down to (3,1); the diagonal (3,1)->(4,2) would cut the wall's
    # corner at (3,2), so it goes down to (4,1) then right: sqrt2 + 2 + 1 + 1
    assert np.isclose(d[4, 2], SQRT2 + 4)
    # and on to (0, 4) on the other side: (4,2) -> (3,3) is again a corner cut, so right to (4,3), then
    # diagonal to (3,4) and up 3
    L = octile_length(free, np.array([0.5, 0.5]), np.array([4.5, 0.5]))
    assert np.isclose(L, SQRT2 + 4 + 1 + SQRT2 + 3)
    assert np.isinf(octile_length(free, np.array([0.5, 0.5]), np.array([2.5, 0.5])))  # blocked goal cell


def test_line_of_sight():
    occ = np.zeros((20, 20), np.uint8)
    occ[5:15, 10] = 1
    sdf = signed_distance_field(occ)
    a = np.array([[3.0, 10.0], [3.0, 2.0]])
    b = np.array([[17.0, 10.0], [17.0, 2.0]])
    assert line_of_sight(sdf, a, b, 1.0).tolist() == [False, True]
