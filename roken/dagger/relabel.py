"""DAgger's relabelling: states the learner visited in closed loop, continued by the Laplacian expert.

The learner drifts into states the expert never showed (the paper's own limitation: "the training data lacks
sufficient examples of such scenarios"). From each rollout we take the last feasible state before its first
violation (the state the model should have recovered from) and states every `state_every` steps before it
(where it was heading), start the expert there with the rollout's goal, and keep the continuation as an
episode of the dataset schema (`source` "dagger", `round` r). The expert only starts from a feasible state
(clearance, spacing, connected): others are refused, with the reason, by `LaplacianExpert.run`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.store import episode_record
from ..eval.harness import PLANNERS
from ..expert.laplacian import ExpertConfig, LaplacianExpert
from ..world.geometry import clearance
from ..world.graph import connected
from ..world.grid import GridMap
from ..world.tasks import Task, TaskConfig, check_start


@dataclass
class DaggerConfig:
    rounds: int = 4  # rollout -> relabel -> train, each round from the previous round's model
    episodes: int = 96  # closed-loop rollouts per round, on `train` maps (new tasks every round)
    # The rollouts' maps: the first this many of the `train` split (None = the whole split, one task per map).
    # A few maps make DAgger's loop small enough to watch converge on two cores (README "Results: DAgger on one map").
    num_maps: int | None = None
    # Every round on round 0's tasks (a fixed, finite task set) instead of new tasks: whether relabelling the
    # learner's own states closes the loop on tasks it keeps meeting, before asking it to generalise.
    same_tasks: bool = False
    robots: int = 4
    state_every: int = 40  # simulator steps between relabelled states along a rollout (10 plan moves)
    max_states: int = 6  # per rollout: the last feasible state before its first violation, then the others
    steps_per_round: int = 1000  # training steps per round on the mix
    share: float = 0.5  # share of training samples drawn from the relabelled episodes of all rounds so far
    sample_steps: int = 0  # training chunks of a relabelled episode start in its first this many steps (0 = anywhere)
    # The learner's own last moves as history: each relabelled episode begins with the rollout's last this many
    # steps before the relabelled state (`sample_from`; chunks start at that state). A model that reads its last
    # move (model.prev_move) then learns the expert's answer to the history it makes itself in closed loop; without
    # it every relabel starts at rest, a zero last move. samples.interval (4) carries one chunk move; 0 = off.
    history_steps: int = 0
    # The planner of the rollouts: plain `roken` (the policy's own distribution, the classic DAgger) or a
    # deployable row (`roken+guided+geodesic`, candidates from plan.candidates), whose episodes reach the later
    # states of a task - the stalls its failures end in - that plain rollouts never get to.
    planner: str = "roken"
    only_failed: bool = False  # relabel only the states of rollouts that failed (a deployable row succeeds often)
    # Self-imitation (expert iteration, as in ReST / RAFT; beyond classic DAgger): the rollouts that succeeded are
    # kept as they were executed, source "self". A deployable row's successes are clean, connected trajectories
    # from the learner's own state distribution, drawn from a mode the model can already represent; training on
    # them distils the guidance and the verified selection into the model's own samples.
    keep_success: bool = False
    seed: int = 0


def check(dc: DaggerConfig) -> None:
    if dc.sample_steps < 0:
        raise ValueError(f"dagger.sample_steps={dc.sample_steps}: must be >= 0 (0 = chunks start anywhere)")
    if dc.history_steps < 0:
        raise ValueError(f"dagger.history_steps={dc.history_steps}: must be >= 0 (0 = relabels start at rest)")
    if dc.num_maps is not None and dc.num_maps < 1:
        raise ValueError(f"dagger.num_maps={dc.num_maps}: must be >= 1; leave it unset (null) to use every train map")
    for k in ("rounds", "episodes", "robots", "state_every", "max_states", "steps_per_round"):
        if getattr(dc, k) < 1:
            raise ValueError(f"dagger.{k} must be >= 1, got {getattr(dc, k)}")
    rows = [p for p in PLANNERS if p.startswith("roken")]  # the harness's rows that roll the learner out
    if dc.planner not in rows:
        raise ValueError(f"dagger.planner={dc.planner!r}: the rollouts are the learner's, one of {', '.join(rows)}")
    if not 0 < dc.share < 1:
        raise ValueError(f"dagger.share={dc.share}: the relabelled episodes' share of training samples must be in "
                         f"(0, 1) (the expert dataset keeps the rest)")


def constraint_steps(positions: np.ndarray, gm: GridMap, tc: TaskConfig) -> np.ndarray:
    """(3, T+1): whether each recorded state keeps clearance, spacing, connectivity (rows in that order)."""
    p = np.asarray(positions, np.float64)
    ok = np.ones((3, len(p)), bool)
    ok[0] = (clearance(gm.padded, p) >= tc.d_obs_min).all(axis=1)
    if p.shape[1] > 1:
        d = np.linalg.norm(p[:, :, None] - p[:, None], axis=-1)
        off = ~np.eye(p.shape[1], dtype=bool)
        ok[1] = (d[:, off] >= tc.d_coll_min).all(axis=1)
        ok[2] = connected(d, tc.comm_radius)
    return ok


def first_violation(positions: np.ndarray, gm: GridMap, tc: TaskConfig) -> tuple[int, np.ndarray]:
    """(the first infeasible step, T+1 if none; which of clearance, spacing, connectivity it breaks, (3,) bool,
    all False if none): an episode's end and its cause (it may break more than one)."""
    ok = constraint_steps(positions, gm, tc)
    bad = np.flatnonzero(~ok.all(axis=0))
    return (int(bad[0]), ~ok[:, bad[0]]) if len(bad) else (len(ok[0]), np.zeros(3, bool))


def feasible_steps(positions: np.ndarray, gm: GridMap, tc: TaskConfig) -> np.ndarray:
    """(T+1,) whether each recorded state satisfies every constraint (clearance, spacing, connected)."""
    return constraint_steps(positions, gm, tc).all(axis=0)


def feasible_span(positions: np.ndarray, gm: GridMap, goal: np.ndarray, leader: int, tc: TaskConfig
                  ) -> tuple[int, int]:
    """(the first infeasible step, T+1 if none; the end of the states worth learning from: that step or the
    leader's arrival at the goal, the earlier)."""
    first_bad, _ = first_violation(positions, gm, tc)
    reached = np.flatnonzero(np.linalg.norm(positions[:, leader] - goal, axis=-1) <= tc.eps_goal)
    return first_bad, min(first_bad, int(reached[0]) if len(reached) else len(positions))


def select_states(positions: np.ndarray, gm: GridMap, goal: np.ndarray, leader: int, tc: TaskConfig,
                  every: int, max_states: int) -> list[int]:
    """The steps of a rollout to relabel: the last feasible step before the first violation (if it failed),
    then every `every` steps before it, the later first (nearer the failure), at most `max_states`; steps
    after the leader reached its goal are not taken (nothing to learn there)."""
    first_bad, end = feasible_span(positions, gm, goal, leader, tc)
    chosen = [first_bad - 1] if 1 <= first_bad <= end and first_bad < len(positions) else []
    chosen += [t for t in range(every, end, every)[::-1] if t not in chosen]
    return sorted(chosen[:max_states])


def relabel(episodes: list[dict], maps: dict[str, GridMap], round_index: int, dc: DaggerConfig,
            tc: TaskConfig, ec: ExpertConfig) -> tuple[list[dict], dict]:
    """Expert continuations from the selected states of `episodes` (rows of a rollout's episodes table).
    Returns the new rows (every one, successful or not: the trainer keeps the successful ones) and counts."""
    tasks, ids, before = [], [], []
    refused = 0
    for ep in episodes:
        if dc.only_failed and bool(ep["success"]):
            continue
        gm = maps[ep["map_id"]]
        P = np.asarray(ep["positions"], np.float64)
        goal, leader = np.asarray(ep["goal"], np.float64), int(ep["leader"])
        for t in select_states(P, gm, goal, leader, tc, dc.state_every, dc.max_states):
            why = check_start(gm, P[t], tc)  # feasible_steps already holds; kept as the expert's own check
            if why:
                refused += 1
                continue
            tasks.append(Task(ep["map_id"], P[t].copy(), goal.copy(), leader, seed=int(ep.get("seed", 0))))
            ids.append(f"dagger-r{round_index:02d}-{ep['episode_id']}-t{t:04d}")
            before.append(P[max(0, t - dc.history_steps):t])  # (h, N, 2): the learner's last steps, h <= history
    rows: list[dict | None] = [None] * len(tasks)
    if tasks:
        expert = LaplacianExpert(ec, tc)
        for i, e in expert.run(tasks, maps):
            h = len(before[i])
            positions = np.concatenate([before[i].astype(e.positions.dtype), e.positions]) if h else e.positions
            rows[i] = episode_record(ids[i], "laplacian", tasks[i], maps[tasks[i].map_id], positions, tc,
                                     tasks[i].seed) | {"source": "dagger", "round": round_index, "sample_from": h,
                                                       "sample_until": dc.sample_steps + h if dc.sample_steps else 0}
    done = [r for r in rows if r is not None]
    kept = [self_record(ep, maps[ep["map_id"]], round_index, dc, tc) for ep in episodes
            if dc.keep_success and bool(ep["success"])]
    stats = {"rollouts": len(episodes), "rollout_success": float(np.mean([bool(e["success"]) for e in episodes]))
             if episodes else 0.0, "states": len(done), "refused": refused,
             "expert_success": float(np.mean([r["success"] for r in done])) if done else 0.0, "self": len(kept)}
    return done + kept, stats


def self_record(ep: dict, gm: GridMap, round_index: int, dc: DaggerConfig, tc: TaskConfig) -> dict:
    """A successful rollout as executed, as an episode of the dataset schema (source "self")."""
    n = int(ep["num_robots"])
    P = np.asarray(ep["positions"], np.float64).reshape(-1, n, 2)
    task = Task(ep["map_id"], P[0].copy(), np.asarray(ep["goal"], np.float64), int(ep["leader"]),
                seed=int(ep.get("seed", 0)))
    return episode_record(f"self-r{round_index:02d}-{ep['episode_id']}", dc.planner, task, gm, P, tc, task.seed) | {
        "source": "self", "round": round_index, "sample_until": 0, "sample_from": 0}
