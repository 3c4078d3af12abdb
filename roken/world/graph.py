"""Communication graphs, weighted Laplacians, lambda_2 and its gradient, spanning trees.

Everything is batched: positions q are (B, N, 2) for B teams of N robots. The edge weight follows
expert.md: A_ij = alpha(d_ij) * gamma_ij with a cosine communication roll-off alpha and a product-form
collision factor gamma over every robot pair and each robot's nearest obstacle. The gradient of lambda_2 is
analytic (centralized: it includes edges that do not touch the robot through the product form of gamma) and
uses the eigenspace projector, so repeated eigenvalues of symmetric trees give a well-defined direction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LOG_FLOOR = 1e-12


@dataclass
class WeightParams:
    comm_radius: float = 15.0  # alpha = 0 beyond (R)
    comm_full: float = 11.0  # alpha = k_a up to here (d_min)
    coll_min: float = 2.0  # g = 0 at or below (d_coll_min)
    coll_full: float = 4.0  # g = k_g beyond (d_coll_max)
    obs_min: float = 1.0  # obstacle factor = 0 at or below this clearance (d_obs_min)
    obs_full: float = 2.5  # obstacle factor = k_g beyond
    k_a: float = 1.0
    k_g: float = 1.0


def cosine_rolloff(d: np.ndarray, lo: float, hi: float, rising: bool, k: float = 1.0):
    """Value and derivative of a cosine step from 0 to k (rising) or k to 0 (falling) over [lo, hi]."""
    s = np.clip((d - lo) / (hi - lo), 0.0, 1.0)
    inside = (d > lo) & (d < hi)
    if rising:
        val = 0.5 * k * (1.0 - np.cos(np.pi * s))
        der = np.where(inside, 0.5 * k * np.pi / (hi - lo) * np.sin(np.pi * s), 0.0)
    else:
        val = 0.5 * k * (1.0 + np.cos(np.pi * s))
        der = np.where(inside, -0.5 * k * np.pi / (hi - lo) * np.sin(np.pi * s), 0.0)
    return val, der


@dataclass
class EdgeWeights:
    """All quantities of one evaluation of the weighted graph, kept for the gradient."""

    dist: np.ndarray  # (B, N, N) pairwise distances
    unit: np.ndarray  # (B, N, N, 2) (q_i - q_j) / d_ij = d d_ij / d q_i
    alpha: np.ndarray  # (B, N, N)
    dalpha: np.ndarray  # (B, N, N)
    gamma: np.ndarray  # (B, N, N)
    h: np.ndarray  # (B, N, N) g'/g of the pair collision factor (0 on the diagonal)
    h_obs: np.ndarray  # (B, N) g_o'/g_o of the obstacle factor
    grad_obs: np.ndarray  # (B, N, 2) gradient of the obstacle distance
    A: np.ndarray  # (B, N, N) weights, 0 on the diagonal and beyond R


def edge_weights(q: np.ndarray, obs_dist: np.ndarray, obs_grad: np.ndarray, p: WeightParams) -> EdgeWeights:
    """Weighted adjacency of the communication graph at positions q (B, N, 2).

    obs_dist (B, N): each robot's distance to the nearest obstacle; obs_grad (B, N, 2) its gradient.
    """
    B, N, _ = q.shape
    diff = q[:, :, None, :] - q[:, None, :, :]  # (B, N, N, 2)
    dist = np.linalg.norm(diff, axis=-1)
    eye = np.eye(N, dtype=bool)[None]
    safe = np.where(eye, 1.0, np.maximum(dist, 1e-9))
    unit = np.where(eye[..., None], 0.0, diff / safe[..., None])
    alpha, dalpha = cosine_rolloff(dist, p.comm_full, p.comm_radius, rising=False, k=p.k_a)
    g, dg = cosine_rolloff(dist, p.coll_min, p.coll_full, rising=True, k=p.k_g)
    g = np.where(eye, 1.0, g)
    dg = np.where(eye, 0.0, dg)
    go, dgo = cosine_rolloff(obs_dist, p.obs_min, p.obs_full, rising=True, k=p.k_g)
    logg = np.log(np.maximum(g, LOG_FLOOR))
    logo = np.log(np.maximum(go, LOG_FLOOR))
    L = logg.sum(axis=2) + logo  # (B, N) log of every factor touching robot i
    loggamma = L[:, :, None] + L[:, None, :] - logg  # the pair (i, j) counted once
    gamma = np.exp(loggamma)
    A = np.where(eye | (dist > p.comm_radius), 0.0, alpha * gamma)
    h = dg / np.maximum(g, LOG_FLOOR)  # guarded log-derivative
    h_obs = dgo / np.maximum(go, LOG_FLOOR)
    return EdgeWeights(dist, unit, alpha, dalpha, gamma, h, h_obs, obs_grad, A)


def laplacian(A: np.ndarray) -> np.ndarray:
    return np.einsum("bij->bi", A)[..., None] * np.eye(A.shape[-1]) - A


def fiedler(A: np.ndarray, tol: float = 1e-6):
    """lambda_2 and the projector form of its eigenspace.

    Returns lam2 (B,), S (B, N, N) with S_ij = (P_ii + P_jj - 2 P_ij) / m where P = U U^T over the m
    eigenvectors whose eigenvalues lie within `tol` (relative) of lambda_2. For a simple eigenvalue this is
    exactly (v_i - v_j)^2; for a repeated one it is the average over the eigenspace, independent of the
    arbitrary basis `eigh` returns.
    """
    w, U = np.linalg.eigh(laplacian(A))
    lam2 = w[:, 1]
    scale = np.maximum(np.abs(w[:, -1:]), 1e-12)
    sel = np.abs(w - lam2[:, None]) <= tol * scale
    sel[:, 0] = False
    sel[:, 1] = True
    m = sel.sum(axis=1)
    P = np.einsum("bik,bjk,bk->bij", U, U, sel.astype(U.dtype)) / m[:, None, None]
    d = np.einsum("bii->bi", P)
    S = d[:, :, None] + d[:, None, :] - 2.0 * P
    return lam2, S


def lambda2_gradient(ew: EdgeWeights, tree: np.ndarray, S: np.ndarray) -> np.ndarray:
    """d lambda_2 / d q (B, N, 2) of the Laplacian restricted to `tree` (B, N, N) bool, symmetric.

    With w_ij = A_ij S_ij on tree edges and W_i = sum_j w_ij:
      grad_m = sum_k [ T_mk alpha'_mk gamma_mk S_mk + (W_m + W_k - w_mk) h_mk ] e_mk + W_m h_obs_m grad_obs_m
    where e_mk = (q_m - q_k)/d_mk. The first term is the communication roll-off on the tree edges at m;
    the second collects d log gamma of every tree edge with respect to q_m (product form, centralized).
    """
    T = tree.astype(np.float64)
    w = T * ew.A * S
    W = w.sum(axis=2)
    C = T * ew.dalpha * ew.gamma * S + (W[:, :, None] + W[:, None, :] - w) * ew.h
    grad = np.einsum("bmk,bmkx->bmx", C, ew.unit)
    grad += (W * ew.h_obs)[..., None] * ew.grad_obs
    return grad


def minimum_spanning_tree(cost: np.ndarray) -> np.ndarray:
    """Batched Prim on dense symmetric costs (B, N, N); inf marks a missing edge.

    Returns the tree's adjacency (B, N, N) bool. Teams whose graph is disconnected get a spanning forest of
    the reachable part from robot 0 (the remaining robots stay isolated).
    """
    B, N, _ = cost.shape
    tree = np.zeros((B, N, N), dtype=bool)
    in_tree = np.zeros((B, N), dtype=bool)
    in_tree[:, 0] = True
    best = cost[:, 0, :].copy()
    best_from = np.zeros((B, N), dtype=np.int64)
    rows = np.arange(B)
    for _ in range(N - 1):
        cand = np.where(in_tree, np.inf, best)
        j = np.argmin(cand, axis=1)
        ok = np.isfinite(cand[rows, j])
        i = best_from[rows, j]
        tree[rows[ok], i[ok], j[ok]] = True
        tree[rows[ok], j[ok], i[ok]] = True
        in_tree[rows[ok], j[ok]] = True
        newc = cost[rows, j, :]
        better = ok[:, None] & (newc < best)
        best = np.where(better, newc, best)
        best_from = np.where(better, j[:, None], best_from)
    return tree


def connected(dist: np.ndarray, radius: float) -> np.ndarray:
    """(B,) whether each team's disk graph (edges d <= radius) is connected."""
    B, N, _ = dist.shape
    reach = (dist <= radius) | np.eye(N, dtype=bool)[None]
    R = reach.astype(np.float32)
    for _ in range(max(1, int(np.ceil(np.log2(max(N, 2)))))):
        R = np.minimum(R @ R, 1.0)
    return R[:, 0, :].min(axis=1) > 0


def tree_parents(tree: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Parent of each robot in `tree` (B, N, N) rooted at `root` (B,); -1 for the root and unreachable."""
    B, N, _ = tree.shape
    parent = np.full((B, N), -1, dtype=np.int64)
    visited = np.zeros((B, N), dtype=bool)
    rows = np.arange(B)
    visited[rows, root] = True
    frontier = visited.copy()
    for _ in range(N - 1):
        # nodes adjacent to the frontier and not visited take a frontier node as parent
        link = tree & frontier[:, :, None] & ~visited[:, None, :]  # (B, from, to)
        has = link.any(axis=1)
        par = np.argmax(link, axis=1)
        parent = np.where(has, par, parent)
        visited |= has
        frontier = has
        if not has.any():
            break
    return parent
