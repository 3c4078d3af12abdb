"""Does plain Roken plan the tasks it was trained on? Closed loop on the tasks of a dataset's own episodes.

    python benchmarks/fit_tasks.py --data data/fit16 --checkpoint runs/fit16 runs/sc-base
    python benchmarks/fit_tasks.py --data data/fit64 --episodes 200 --checkpoint runs/fit64 runs/sc-base

Evaluation tasks are drawn from their own seed stream, so they never coincide with a dataset's. This takes the
tasks of a dataset's (or an evaluation folder's) recorded episodes, the first `--episodes` of team size
`--robots` by episode id: the same map, starts, goal and leader the expert was recorded on, and runs each
checkpoint on them in closed loop (`--planner`, plain `roken` by default; the planner settings of `--set plan.*`).
A model trained on that dataset has seen the expert's answer at every state of these episodes: if it plans them,
its precision is what it fits; if it fails them too, closed loop breaks what the open-loop fit learned. Prints
the compact metrics, the median simulator step of the first constraint violation and what it breaks, per
checkpoint, and the expert's own row (the recorded episodes scored the same way).
"""
from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from roken.config import load_config
from roken.dagger.relabel import first_violation
from roken.data.store import read_run
from roken.plan.controller import rollout_config
from roken.eval.metrics import COMPACT_HEAD, compact_cells, summarize
from roken.plan import RokenPlanner, RokenRollout
from roken.world.metrics import episode_metrics
from roken.world.tasks import Task


def dataset_tasks(folder: str, robots: int, episodes: int) -> tuple[dict, list[Task], list[np.ndarray]]:
    """(maps by id, tasks, the recorded positions) of the first `episodes` episodes with `robots` robots."""
    maps, rows = read_run(folder)
    rows = sorted((r for r in rows if r["num_robots"] == robots and r.get("planner", "laplacian") == "laplacian"),
                  key=lambda r: r["episode_id"])[:episodes]
    if not rows:
        raise SystemExit(f"--data {folder}: no expert episode with {robots} robots; pick --robots from the folder's "
                         f"team sizes")
    tasks = [Task(r["map_id"], np.asarray(r["positions"][0], np.float64), np.asarray(r["goal"], np.float64),
                  int(r["leader"]), seed=int(r.get("seed") or 0)) for r in rows]
    return maps, tasks, [np.asarray(r["positions"]) for r in rows]


def row(name: str, runs: list[np.ndarray], tasks: list[Task], by_id: dict, tc, seconds: float) -> str:
    metrics, first, kinds = [], [], np.zeros(3, int)
    for P, t in zip(runs, tasks):
        gm = by_id[t.map_id]
        metrics.append(episode_metrics(P, gm, t.goal, t.leader, tc))
        at, broken = first_violation(P, gm, tc)  # broken: clearance, spacing, connectivity
        if broken.any():
            first.append(at)
            kinds += broken
    viol = f"{np.median(first):.0f} ({len(first)} ep.)" if first else "-"
    return f"{name:<28}{compact_cells(summarize(metrics))}{viol:>20}{'/'.join(map(str, kinds)):>18}{seconds:>6.0f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a dataset or evaluation folder whose expert episodes give the tasks")
    ap.add_argument("--checkpoint", nargs="+", required=True, help="checkpoints or run folders")
    ap.add_argument("--planner", default="roken", help="roken | roken+guided | roken+safe ... (the row's planner)")
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--set", action="append", default=[], help="config overrides, e.g. plan.noise_scale=0.5")
    args = ap.parse_args()
    if args.episodes < 1:
        raise SystemExit(f"--episodes {args.episodes}: must be >= 1")
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    cfg = load_config(None, args.set)
    by_id, tasks, recorded = dataset_tasks(args.data, args.robots, args.episodes)
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, 1 thread; "
          f"{len(tasks)} tasks of {args.data}'s episodes, N = {args.robots}, {args.planner}", flush=True)
    head = f"{'planner':<28}{COMPACT_HEAD}{'1st viol. (median)':>20}{'obs./inter/conn.':>18}{'s':>6}"
    lines = [head, "-" * len(head), row("expert (recorded)", recorded, tasks, by_id, cfg.task, 0.0)]
    print("\n".join(lines), flush=True)
    for c in args.checkpoint:
        t0 = time.perf_counter()
        planner = RokenPlanner.load(c, "cpu", "fp32", cfg.plan.which, cfg.task.max_step)
        rollout = RokenRollout(planner, rollout_config(cfg.plan, args.planner), cfg.task, cfg.expert)
        runs: list[np.ndarray | None] = [None] * len(tasks)
        for i, pos, _ in rollout.run(tasks, by_id):
            runs[i] = np.asarray(pos)
        lines.append(row(f"{args.planner} {c}", runs, tasks, by_id, cfg.task, time.perf_counter() - t0))
        print(lines[-1], flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
