"""Navigation tasks: a connected, collision-free start configuration, a leader and its goal."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import clearance, line_of_sight
from .grid import GridMap


@dataclass
class TaskConfig:
    comm_radius: float = 15.0  # R
    d_coll_min: float = 2.0
    d_obs_min: float = 1.0
    eps_goal: float = 1.0
    max_step: float = 0.5
    min_goal_distance: float = 50.0  # Euclidean, leader start -> goal
    start_spacing_min: float = 3.0  # a follower starts this far or farther from every robot
    start_spacing_max: float = 10.0  # ... and at most this far from the robot it is attached to
    start_jitter: float = 0.25  # starts are safe-cell centres moved by up to this much
    max_retries: int = 200


@dataclass
class Task:
    map_id: str
    starts: np.ndarray  # (N, 2) float64 (x, y)
    goal: np.ndarray  # (2,) float64
    leader: int
    seed: int = 0

    @property
    def num_robots(self) -> int:
        return len(self.starts)


class TaskError(ValueError):
    """A map that cannot host the requested task, with the reason."""


def check_start(gm: GridMap, starts: np.ndarray, cfg: TaskConfig) -> str | None:
    """Why `starts` is not a valid start configuration, or None when it is."""
    clear = clearance(gm.padded, starts)
    if (clear < cfg.d_obs_min).any():
        return f"robot {int(np.argmin(clear))} is {clear.min():.2f} m from an obstacle"
    d = np.linalg.norm(starts[:, None] - starts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    if (d < cfg.d_coll_min).any():
        return f"two robots start {d.min():.2f} m apart"
    adj = d <= cfg.comm_radius
    seen = {0}
    frontier = [0]
    while frontier:
        i = frontier.pop()
        for j in np.nonzero(adj[i])[0]:
            if j not in seen:
                seen.add(int(j))
                frontier.append(int(j))
    if len(seen) < len(starts):
        return "the start communication graph is disconnected"
    return None


def sample_task(gm: GridMap, num_robots: int, cfg: TaskConfig, rng: np.random.Generator,
                seed: int = 0) -> Task:
    """Sample a task on `gm`; raises TaskError with the reason after `cfg.max_retries` attempts."""
    if num_robots < 1:
        raise TaskError(f"num_robots must be >= 1, got {num_robots}")
    graph = gm.safe_graph
    cells = graph.cells
    if len(cells) == 0:
        raise TaskError(f"map {gm.map_id}: no free cell has a free 3 x 3 neighbourhood, "
                        "so no robot can stand anywhere with clearance")
    centres = np.stack([cells[:, 1] + 0.5, cells[:, 0] + 0.5], axis=1).astype(np.float64)
    reasons: dict[str, int] = {}

    def fail(why: str):
        reasons[why] = reasons.get(why, 0) + 1

    for _ in range(cfg.max_retries):
        s = int(rng.integers(len(cells)))
        region = np.nonzero(graph.component == graph.component[s])[0]
        far = region[np.linalg.norm(centres[region] - centres[s], axis=1) >= cfg.min_goal_distance]
        if len(far) == 0:
            fail(f"no goal >= {cfg.min_goal_distance:g} m away in the start's free region")
            continue
        goal = centres[int(rng.choice(far))]
        placed = [centres[s] + rng.uniform(-cfg.start_jitter, cfg.start_jitter, 2)]
        in_region = np.zeros(len(cells), dtype=bool)
        in_region[region] = True
        ok = True
        for _k in range(num_robots - 1):
            ok = False
            for _try in range(60):
                anchor = placed[int(rng.integers(len(placed)))]
                r = rng.uniform(cfg.start_spacing_min, cfg.start_spacing_max)
                th = rng.uniform(0, 2 * np.pi)
                p = anchor + r * np.array([np.cos(th), np.sin(th)])
                node = graph.node_of(p)
                if node < 0 or not in_region[node]:
                    continue
                p = centres[node] + rng.uniform(-cfg.start_jitter, cfg.start_jitter, 2)
                if min(np.linalg.norm(q - p) for q in placed) < cfg.start_spacing_min:
                    continue
                if np.linalg.norm(anchor - p) > cfg.start_spacing_max + 1.0:
                    continue
                if not line_of_sight(gm.sdf, anchor, p, cfg.d_obs_min):
                    continue
                placed.append(p)
                ok = True
                break
            if not ok:
                break
        if not ok:
            fail(f"no room for {num_robots} robots spaced {cfg.start_spacing_min:g}.."
                 f"{cfg.start_spacing_max:g} m around the start")
            continue
        starts = np.array(placed)
        why = check_start(gm, starts, cfg)
        if why:
            fail(why)
            continue
        # the leader is placed first; give it a random index so no model can learn "robot 0 leads"
        order = rng.permutation(num_robots)
        starts = starts[np.argsort(order)]
        leader = int(order[0])
        return Task(map_id=gm.map_id, starts=starts, goal=goal.copy(), leader=leader, seed=seed)
    summary = "; ".join(f"{why} ({n}x)" for why, n in sorted(reasons.items(), key=lambda kv: -kv[1]))
    raise TaskError(f"map {gm.map_id}: no {num_robots}-robot task after {cfg.max_retries} attempts: {summary}")
