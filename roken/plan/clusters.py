"""Overlapping clusters for clustered rollout (paper appendix, "Masked Training and Clustered Rollout").

A team larger than the model's training teams is planned cluster by cluster, each cluster one conditional
generation with the robots already planned in earlier clusters given as fixed trajectories:
  1. the communication graph (edges ||p_i - p_j|| <= R);
  2. a BFS tree rooted at the leader (children in order of distance to their parent);
  3. the first cluster is the leader and its BFS descendants up to `size`; every later cluster is rooted at an
     already planned robot with unplanned children: it takes up to `new` of those children, then fills up to
     `size` with planned robots as conditions: the root, the new children's planned siblings, then the root's
     ancestors and siblings, then the planned robots nearest the root. `new = 1` is the paper's bias to its
     case (3): three given robots and one generated child, the most informative condition, at the cost of more
     clusters.
A robot out of range of the leader's component starts its own tree (its first cluster has neither goal nor
condition). Every robot is generated exactly once.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Cluster:
    members: np.ndarray  # (m,) robot indices into the team
    fixed: np.ndarray  # (m,) bool: given as conditions (planned in an earlier cluster)
    leader: int  # index of the team's leader within members, -1 if it is not a member

    @property
    def generated(self) -> np.ndarray:
        return self.members[~self.fixed]


def bfs_tree(positions: np.ndarray, leader: int, radius: float) -> tuple[np.ndarray, list[int]]:
    """(parent (N,) with -1 at roots, BFS order over all robots); roots: the leader, then the lowest-index
    robot of each component the leader cannot reach."""
    N = len(positions)
    d = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    near = (d <= radius) & ~np.eye(N, dtype=bool)
    parent = np.full(N, -1)
    seen = np.zeros(N, bool)
    order: list[int] = []
    for root in [leader] + list(range(N)):
        if seen[root]:
            continue
        seen[root] = True
        queue = [root]
        while queue:
            v = queue.pop(0)
            order.append(v)
            nbrs = np.flatnonzero(near[v] & ~seen)
            for c in nbrs[np.argsort(d[v, nbrs], kind="stable")]:
                seen[c], parent[c] = True, v
                queue.append(int(c))
    return parent, order


def overlapping_clusters(positions: np.ndarray, leader: int, radius: float, size: int = 4,
                         new: int = 1) -> list[Cluster]:
    """The clusters of a team at positions (N, 2), in generation order (module docstring)."""
    if size < 2:
        raise ValueError(f"cluster_size must be >= 2 (a given robot and a generated one), got {size}")
    new = max(1, min(new, size - 1))
    N = len(positions)
    parent, order = bfs_tree(np.asarray(positions, np.float64), leader, radius)
    children = [[c for c in order if parent[c] == v] for v in range(N)]
    rank = {v: i for i, v in enumerate(order)}
    planned = np.zeros(N, bool)
    clusters: list[Cluster] = []

    def make(members: list[int], fixed: list[bool]) -> Cluster:
        m = np.asarray(members)
        hit = np.flatnonzero(m == leader)
        return Cluster(m, np.asarray(fixed, bool), int(hit[0]) if len(hit) else -1)

    for v in order:
        if planned[v] or parent[v] >= 0:
            continue
        # a root (the leader first): it and its BFS descendants, in BFS order, up to `size`
        comp = [v]
        for u in order[rank[v] + 1:]:
            w = u
            while parent[w] >= 0 and w != v:
                w = parent[w]
            if w == v and len(comp) < size:
                comp.append(u)
        clusters.append(make(comp, [False] * len(comp)))
        planned[comp] = True
        while True:
            root = next((u for u in order if planned[u] and any(not planned[c] for c in children[u])), None)
            if root is None:
                break
            todo = [c for c in children[root] if not planned[c]]
            gen = todo[:new]
            cond = [root]
            fill = [c for c in children[root] if planned[c]]  # the new children's planned siblings
            a = root
            while parent[a] >= 0:  # ancestors, each followed by its planned children (the root's siblings first)
                a = parent[a]
                fill += [a] + [c for c in children[a] if planned[c]]
            dist = np.linalg.norm(positions - positions[root], axis=-1)
            fill += [int(u) for u in np.argsort(dist, kind="stable") if planned[u]]
            for u in fill:
                if len(cond) + len(gen) >= size:
                    break
                if u not in cond:
                    cond.append(u)
            gen += todo[len(gen):len(gen) + size - len(cond) - len(gen)]  # room left: more new children
            clusters.append(make(cond + gen, [True] * len(cond) + [False] * len(gen)))
            planned[gen] = True
    return clusters
