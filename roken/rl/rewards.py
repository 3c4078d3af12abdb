"""GRPO's reward with privileged information (paper appendix; used only in training, never by a planner).

A candidate is a team chunk: H planned points per robot, one every `interval` simulator steps. It is scored as
it would run: each chunk move is executed as `interval` simulator steps clipped to max_step by their norm (the
closed-loop executor's rule), and every simulator step is checked. With n robots, S = H * interval steps:

  C_obs    w_obs   x planned robot points with clearance < d_obs_min + obs_margin   (soft margin count)
  C_inter  w_inter x planned pair points closer than d_coll_min + inter_margin       (soft margin count)
  C_conn   w_conn  x disconnected simulator steps (disk graph, comm_radius)
  C_goal   w_goal  x (1 + (g_end - g_start) / (H * interval * max_step)), clipped at 0: the leader's geodesic
                     (octile, true map) distance to the goal at the chunk's end, in units of a chunk at full
                     speed: 0 for full-speed progress, 1 for none, 2 for full speed backwards
  C_wp     w_wp    x mean over the leader's planned points of the distance (in wp_scale metres) to the nearest
                     waypoint of the optimal path (the expert's A* reference from the prompt state)
  bonus    -reach_bonus once the leader is within eps_goal of the goal

The soft counts are taken at the H planned points (not every simulator step, which would weigh a near miss 4x
against goal progress); a hard violation (clearance < d_obs_min, a pair closer than d_coll_min, a disconnected
step) is checked at every simulator step and adds hard_cost (the paper's c_max by default), and
r = -min(C, c_max) / reward_scale. Everything is vectorised over the G candidates of a group.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..expert.reference import leader_reference
from ..plan.rollout import step_toward
from ..plan.select import geodesic_field, lookup
from ..world.geometry import clearance
from ..world.graph import connected
from ..world.grid import GridMap
from ..world.tasks import TaskConfig
from .config import RLConfig

REF_CLEARANCE = 1.6  # the expert's reference clearance (expert.ref_clearance)


@dataclass
class Privileged:
    """What the simulator knows about one prompt: the true map's fields, the goal's geodesic field and the
    optimal path's waypoints from the leader's position."""
    gm: GridMap
    goal: np.ndarray  # (2,)
    leader: int
    geodesic: np.ndarray  # (S, S) octile distance to the goal's cell, inf on blocked / unreachable cells
    waypoints: np.ndarray  # (W, 2) along the optimal path, 1 m apart, covering a chunk at full speed


def geodesic_to(gm: GridMap, goal: np.ndarray) -> np.ndarray:
    """Octile distance to the goal on the true map (the free-cell graph GridMap keeps)."""
    return geodesic_field(gm.occupancy, goal, gm.free_graph)


def privileged(gm: GridMap, positions: np.ndarray, leader: int, goal: np.ndarray, reach: float,
               geodesic: np.ndarray | None = None) -> Privileged:
    """The privileged information of the state (positions (n, 2), leader, goal); `reach` metres of the optimal
    path are kept as waypoints. `geodesic` may be passed when cached per (map, goal)."""
    goal = np.asarray(goal, np.float64)
    ref = leader_reference(gm, np.asarray(positions[leader], np.float64), goal, REF_CLEARANCE, 1.0)
    if ref is None:  # no safe path: the straight line is the best waypoint guess left
        ref = np.stack([positions[leader], goal]).astype(np.float64)
    seg = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref, axis=0), axis=1))])
    wps = ref[seg <= reach + 1.0]
    return Privileged(gm, goal, int(leader), geodesic_to(gm, goal) if geodesic is None else geodesic, wps)


def simulate(start: np.ndarray, plan: np.ndarray, interval: int, max_step: float) -> np.ndarray:
    """Simulator positions of chunks plan (G, n, H, 2) from start (n, 2): (G, H * interval + 1, n, 2), start
    first, stepped exactly as roken.plan.rollout executes a plan."""
    G, n, H, _ = plan.shape
    q = np.broadcast_to(np.asarray(start, np.float64), (G, n, 2)).copy()
    out, prev = [q.copy()], q.copy()
    for j in range(H):
        target = plan[:, :, j].astype(np.float64)
        for k in range(1, interval + 1):
            q = q + step_toward(q, prev, target, k, interval, max_step)
            out.append(q.copy())
        prev = target
    return np.stack(out, axis=1)


def score(plan: np.ndarray, start: np.ndarray, info: Privileged, tc: TaskConfig, rc: RLConfig,
          interval: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Rewards (G,) of candidate chunks plan (G, n, H, 2) in metres from start (n, 2), and per-candidate terms:
    cost, hard (any hard violation), obs / inter / conn (hard violations of each kind), reach."""
    G, n, H, _ = plan.shape
    q = simulate(start, plan, interval, tc.max_step)  # (G, S+1, n, 2)
    steps = q[:, 1:]
    clear = clearance(info.gm.padded, steps.reshape(-1, 2)).reshape(G, -1, n)
    planned = np.arange(interval - 1, H * interval, interval)  # the steps that end a chunk move
    obs_hard = (clear < tc.d_obs_min).any(axis=(1, 2))
    c_obs = (clear[:, planned] < tc.d_obs_min + rc.obs_margin).sum(axis=(1, 2))
    if n > 1:
        d = np.linalg.norm(steps[:, :, :, None] - steps[:, :, None], axis=-1)  # (G, S, n, n)
        iu = np.triu_indices(n, 1)
        pair = d[:, :, iu[0], iu[1]]
        inter_hard = (pair < tc.d_coll_min).any(axis=(1, 2))
        c_inter = (pair[:, planned] < tc.d_coll_min + rc.inter_margin).sum(axis=(1, 2))
        disc = ~connected(d.reshape(-1, n, n), tc.comm_radius).reshape(G, -1)
        conn_hard, c_conn = disc.any(axis=1), disc.sum(axis=1)
    else:
        inter_hard = conn_hard = np.zeros(G, bool)
        c_inter = c_conn = np.zeros(G)
    lead = q[:, :, info.leader]  # (G, S+1, 2)
    g0 = lookup(info.geodesic, lead[:1, 0])[0]
    g1 = lookup(info.geodesic, lead[:, -1])
    full = H * interval * tc.max_step
    g0 = g0 if np.isfinite(g0) else np.linalg.norm(lead[0, 0] - info.goal)
    g1 = np.where(np.isfinite(g1), g1, g0 + full)  # ending inside an obstacle counts as full speed backwards
    c_goal = np.maximum(0.0, 1.0 + (g1 - g0) / full)
    pts = plan[:, info.leader].astype(np.float64)  # (G, H, 2)
    dev = np.linalg.norm(pts[:, :, None] - info.waypoints[None, None], axis=-1).min(axis=-1).mean(axis=1)
    reach = (np.linalg.norm(lead - info.goal, axis=-1) <= tc.eps_goal).any(axis=1)
    hard = obs_hard | inter_hard | conn_hard
    cost = (rc.w_obs * c_obs + rc.w_inter * c_inter + rc.w_conn * c_conn + rc.w_goal * c_goal
            + rc.w_wp * dev / rc.wp_scale - rc.reach_bonus * reach + rc.hard_cost * hard)
    reward = -np.minimum(cost, rc.c_max) / rc.reward_scale
    return reward.astype(np.float32), {"cost": cost, "hard": hard, "obs": obs_hard, "inter": inter_hard,
                                       "conn": conn_hard, "reach": reach, "goal": c_goal, "wp": dev}
