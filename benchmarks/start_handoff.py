"""How much of plain Roken's failure is the start? The expert drives the first K steps, then the model.

    python benchmarks/start_handoff.py --checkpoint models/roken-cpu-four-dagger                 # 200 eval tasks
    python benchmarks/start_handoff.py --checkpoint runs/pm-a --steps 0,8,16,32,64 --planner roken+guided

Plain Roken's episodes fail early: the first inter-robot contact comes at a median of 26-30 simulator steps, from
an at-rest start where the team stands 3-4 m apart and the models' followers' first moves are unrelated to the
expert's (README "The last move as an input, and the start of an episode"). This runs the Table-1 tasks with the
Laplacian expert for their first K simulator steps (its own episode, recorded as in the datasets), then hands the
team to the model in closed loop (`RokenRollout.run(prefixes=...)`: the expert's last move is the model's history,
the task's own step limit covers the whole episode, the metrics read the whole episode). K = 0 is the plain row.
Each row says what plain success would be if the model's first K steps were the expert's: if it climbs with K, the
start is what plain Roken lacks; if it stays low, the model's precision mid-episode is.
Episodes the expert finishes within K steps are its own (counted in `expert-done`).
Measured (README "Handing the start to the expert"): it stays low; from any expert state the models break a
constraint a median of 25-34 steps after the hand-over.
"""
from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import numpy as np
import torch

from roken.config import load_config
from roken.dagger.relabel import constraint_steps, first_violation
from roken.plan.controller import rollout_config
from roken.eval.harness import load_maps, make_tasks
from roken.eval.metrics import COMPACT_HEAD, compact_cells, summarize
from roken.expert.laplacian import LaplacianExpert
from roken.plan import RokenPlanner, RokenRollout
from roken.world.tasks import Task, check_start
from roken.world.metrics import episode_metrics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--planner", default="roken", help="roken | roken+guided | roken+safe ... (the row's planner)")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--maps", default="eval")
    ap.add_argument("--steps", default="0,8,16,32,64,128", help="K: simulator steps driven by the expert first")
    ap.add_argument("--replans", type=int, default=0, help="R > 0: also the executed-move error of the first R "
                    "re-plans after each hand-over, against the expert restarted at the same state")
    ap.add_argument("--set", action="append", default=[], help="config overrides, e.g. plan.noise_scale=0.5")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    cfg = load_config(None, [f"eval.maps={args.maps}", f"eval.episodes={args.episodes}"] + args.set)
    ks = [int(k) for k in args.steps.split(",")]
    if min(ks) < 0:
        raise ValueError(f"--steps {args.steps}: each K must be >= 0 simulator steps")
    maps, _ = load_maps(cfg)
    by_id = {m.map_id: m for m in maps}
    tasks = [t for _, t in make_tasks(cfg, maps, args.robots)[0]]
    planner = RokenPlanner.load(args.checkpoint, "cpu", "fp32", cfg.plan.which, cfg.task.max_step)
    rollout = RokenRollout(planner, rollout_config(cfg.plan, args.planner), cfg.task, cfg.expert)
    t0 = time.perf_counter()
    expert = dict(LaplacianExpert(cfg.expert, cfg.task).run(tasks, by_id))
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, 1 thread; "
          f"{len(tasks)} `{args.maps}` tasks, N = {args.robots}, {args.planner} of {planner.source}; the expert's "
          f"episodes in {time.perf_counter() - t0:.0f} s", flush=True)
    head = f"{'K':>5}{'expert-done':>12}{COMPACT_HEAD}" \
           f"{'1st viol. after K (median)':>28}{'of which obs./inter/conn.':>27}{'s':>6}"
    lines = [head, "-" * len(head)]
    print(head, flush=True)
    errors = []
    for K in ks:
        t0 = time.perf_counter()
        pos = {i: ep.positions for i, ep in expert.items() if len(ep.positions) - 1 <= K}  # the expert finished
        rest = [i for i in range(len(tasks)) if i not in pos]
        prefixes = [expert[i].positions[:K + 1] for i in rest]
        for j, p, _ in rollout.run([tasks[i] for i in rest], by_id, prefixes):
            pos[rest[j]] = p
        rows, after, kinds = [], [], np.zeros(3, int)
        for i, t in enumerate(tasks):
            gm = by_id[t.map_id]
            rows.append(episode_metrics(np.asarray(pos[i]), gm, np.asarray(t.goal), t.leader, cfg.task))
            if i not in rest:
                continue
            at, broken = first_violation(pos[i][K:], gm, cfg.task)  # broken: clearance, spacing, connectivity
            if broken.any():
                after.append(at)
                kinds += broken  # what the first infeasible step breaks (it may break more than one)
        m = summarize(rows)
        lines.append(f"{K:>5}{len(tasks) - len(rest):>12}{compact_cells(m)}"
                     f"{(f'{np.median(after):.0f} ({len(after)} ep.)' if after else '-'):>28}"
                     f"{'/'.join(str(k) for k in kinds):>27}"
                     f"{time.perf_counter() - t0:>6.0f}")
        print(lines[-1], flush=True)
        if args.replans > 0:
            errors += [(K,) + r for r in replan_error(cfg, tasks, by_id, expert, {i: pos[i] for i in rest}, K,
                                                     args.replans)]
    print("\n".join(lines))
    if errors:
        head = f"{'K':>5}{'re-plan':>8}{'model: states':>15}{'executed L2':>13}{'followers':>11}" \
               f"{'expert: states':>16}{'executed L2':>13}{'followers':>11}"
        print("\nexecuted-move error (m) after the hand-over, against the Laplacian expert restarted (warm) at the "
              "same state;\nthe recorded expert's own error there is the floor (its labels' spread given the state)")
        print(head + "\n" + "-" * len(head))
        for K, j, n, e, f, n0, e0, f0 in errors:
            print(f"{K:>5}{j + 1:>8}{n:>15}{e:>13.3f}{f:>11.3f}{n0:>16}{e0:>13.3f}{f0:>11.3f}")


def replan_error(cfg, tasks, by_id, expert, runs: dict, K: int, R: int) -> list[tuple]:
    """(re-plan j, states, mean executed L2, followers' L2) x (the model's episodes `runs`, the recorded expert's)
    for the first R re-plans after the hand-over at K: at each re-plan state with no violation yet the
    Laplacian expert restarts with its inertia warm (`expert.warm_start`) and its executed chunk points are compared
    with what the team then did; for the recorded expert that is its labels' own spread ("Markov labels")."""
    tc, I, E = cfg.task, cfg.samples.interval, cfg.plan.replan_every
    ec = dataclasses.replace(cfg.expert, step_limit_factor=0.0, step_limit_extra=E * I + 1, warm_start=True)
    cols = []
    for source in (runs, {i: expert[i].positions for i in runs}):
        starts, done, at = [], [], []
        for i, P in source.items():
            t, gm = tasks[i], by_id[tasks[i].map_id]
            P = np.asarray(P, np.float64)
            ok = np.cumprod(constraint_steps(P[K:], gm, tc).all(axis=0)).astype(bool)  # feasible so far
            for j in range(R):
                s = K + j * E * I
                if s + E * I > len(P) - 1 or not ok[s - K] or check_start(gm, P[s], tc):
                    break
                starts.append(Task(t.map_id, P[s].copy(), t.goal, t.leader, seed=t.seed))
                done.append((P[s + I * np.arange(1, E + 1)], t.leader))
                at.append(j)
        d = np.zeros((len(starts), tasks[0].num_robots))  # (states, N): each robot's mean over the E points
        for k, q in LaplacianExpert(ec, tc).run(starts, by_id):
            Q = q.positions.astype(np.float64)
            d[k] = np.linalg.norm(Q[np.minimum(I * np.arange(1, E + 1), len(Q) - 1)] - done[k][0], axis=-1).mean(0)
        at = np.asarray(at)
        col = []
        for j in range(R):
            rows = np.flatnonzero(at == j)
            fol = [np.delete(d[k], done[k][1]).mean() for k in rows]
            col.append((len(rows), float(d[rows].mean()) if len(rows) else np.nan,
                        float(np.mean(fol)) if fol else np.nan))
        cols.append(col)
    return [(j,) + cols[0][j] + cols[1][j] for j in range(R)]


if __name__ == "__main__":
    main()
