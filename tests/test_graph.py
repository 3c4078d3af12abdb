import numpy as np

from roken.world.graph import (WeightParams, connected, edge_weights, fiedler, lambda2_gradient,
                               minimum_spanning_tree, tree_parents)


def _lam2(q, obs, grad_obs, tree, p):
    ew = edge_weights(q, obs, grad_obs, p)
    lam2, S = fiedler(ew.A * tree)
    return lam2, ew, S


def test_lambda2_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    p = WeightParams()
    # a stretched chain with robots close to each other and to an obstacle, so every term is active
    q = np.array([[[0.0, 0.0], [12.5, 0.8], [15.2, 2.5], [26.0, 3.0], [17.0, 6.0]]])
    q = q + rng.normal(0, 0.05, q.shape)
    # obstacle distance: a wall at y = -1.7, distance = y + 1.7, gradient (0, 1)
    obs_f = lambda q: (q[..., 1] + 1.7)
    grad_obs = np.zeros_like(q)
    grad_obs[..., 1] = 1.0
    dist = np.linalg.norm(q[:, :, None] - q[:, None], axis=-1)
    cost = np.where((dist <= p.comm_radius) & ~np.eye(5, dtype=bool), dist, np.inf)
    tree = minimum_spanning_tree(cost)
    lam2, ew, S = _lam2(q, obs_f(q), grad_obs, tree, p)
    g = lambda2_gradient(ew, tree, S)
    h = 1e-6
    num = np.zeros_like(q)
    for i in range(5):
        for k in range(2):
            qp, qm = q.copy(), q.copy()
            qp[0, i, k] += h
            qm[0, i, k] -= h
            num[0, i, k] = (_lam2(qp, obs_f(qp), grad_obs, tree, p)[0][0]
                                - _lam2(qm, obs_f(qm), grad_obs, tree, p)[0][0]) / (2 * h)
    assert np.abs(num).max() > 1e-3  # the configuration exercises the gradient
    np.testing.assert_allclose(g, num, atol=1e-6, rtol=1e-4)


def test_lambda2_of_known_graphs():
    # unit path graph P_n: lambda_2 = 2 (1 - cos(pi / n)); star S_n: 1; complete K_n: n
    for n in (2, 4, 7, 10):
        A = np.zeros((1, n, n))
        i = np.arange(n - 1)
        A[0, i, i + 1] = A[0, i + 1, i] = 1.0
        assert np.isclose(fiedler(A)[0][0], 2 * (1 - np.cos(np.pi / n)))
        star = np.zeros((1, n, n))
        star[0, 0, 1:] = star[0, 1:, 0] = 1.0
        assert np.isclose(fiedler(star)[0][0], 1.0 if n > 2 else 2.0)
        K = np.ones((1, n, n)) - np.eye(n)
        assert np.isclose(fiedler(K)[0][0], n)


def test_repeated_eigenvalue_projector_is_basis_independent():
    # a star has lambda_2 = 1 with multiplicity n - 2: S must not depend on eigh's arbitrary basis
    n = 5
    star = np.zeros((1, n, n))
    star[0, 0, 1:] = star[0, 1:, 0] = 1.0
    perm = np.array([0, 3, 1, 4, 2])
    _, S1 = fiedler(star)
    _, S2 = fiedler(star[:, perm][:, :, perm])
    np.testing.assert_allclose(S1[0][np.ix_(perm, perm)], S2[0], atol=1e-9)
    # leaves are symmetric: every leaf-centre entry equal
    assert np.allclose(S1[0, 0, 1:], S1[0, 0, 1])


def test_mst_on_known_graph_and_parents():
    inf = np.inf
    cost = np.array([[[inf, 1, 4, inf],
                      [1, inf, 2, 6],
                      [4, 2, inf, 3],
                      [inf, 6, 3, inf]]])
    tree = minimum_spanning_tree(cost)
    edges = {tuple(sorted(e)) for e in zip(*np.nonzero(tree[0]))}
    assert edges == {(0, 1), (1, 2), (2, 3)}
    par = tree_parents(tree, np.array([3]))
    assert par.tolist() == [[1, 2, 3, -1]]


def test_connected():
    q = np.array([[[0, 0], [10, 0], [20, 0]], [[0, 0], [10, 0], [40, 0]]], float)
    d = np.linalg.norm(q[:, :, None] - q[:, None], axis=-1)
    assert connected(d, 15.0).tolist() == [True, False]
