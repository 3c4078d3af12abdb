"""Paired comparison of two evaluations on the same tasks (`roken compare A [B]`).

Two rows of a results table each carry a standard error of sqrt(p (1 - p) / n), about 0.034 on 200 tasks, yet
most tasks are solved by both planners or by neither. What tells them apart is the tasks only one of them
solves: under "no difference" each such task is a fair coin, so the exact two-sided sign test on them
(McNemar's exact test) gives the p-value the README's comparisons quote. Rows are joined on the task seed and
the tasks are checked to be the same (map, leader, goal, starts) before anything is counted.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from ..data import fs
from ..data.store import read_episode_columns

COLUMNS = ["planner", "num_robots", "seed", "map_id", "leader", "goal", "positions", "success", "reach"]
METRICS = ("success", "reach")


@dataclass
class Paired:
    planner_a: str
    planner_b: str
    robots: int
    tasks: int
    rate_a: float
    rate_b: float
    only_a: int  # tasks A solves and B does not
    only_b: int
    p_value: float  # exact two-sided sign test on the only_a + only_b discordant tasks


def episode_files(run: str | Path) -> dict[tuple[str, int], dict]:
    """(planner, team size) -> {seed: row} for every episodes file of an evaluation (or dataset) folder."""
    files = fs.list_files(fs.join(run, "episodes"), ".parquet")
    if not files:
        raise ValueError(f"{run}: no episodes/*.parquet (an evaluation folder written by pipelines/evaluate.py)")
    out: dict[tuple[str, int], dict] = {}
    for f in files:
        for r in read_episode_columns(f, COLUMNS).to_pylist():
            out.setdefault((r["planner"], r["num_robots"]), {})[r["seed"]] = r
    return out


def _same_task(a: dict, b: dict) -> bool:
    n = a["num_robots"] * 2
    return (a["map_id"] == b["map_id"] and a["leader"] == b["leader"]
            and np.allclose(a["goal"], b["goal"]) and np.allclose(a["positions"][:n], b["positions"][:n]))


def pair(rows_a: dict, rows_b: dict, metric: str = "success") -> tuple[int, float, float, int, int, float]:
    """(tasks, rate A, rate B, only A, only B, p) over the seeds both evaluated; raises on different tasks."""
    seeds = sorted(set(rows_a) & set(rows_b))
    if not seeds:
        raise ValueError("no task seed in common: evaluate both with the same --maps / --episodes / eval.seed")
    for s in seeds:
        if not _same_task(rows_a[s], rows_b[s]):
            raise ValueError(f"task seed {s} is not the same task in both (map {rows_a[s]['map_id']} vs "
                             f"{rows_b[s]['map_id']}): evaluate both with the same map, task and eval settings")
    a = np.array([bool(rows_a[s][metric]) for s in seeds])
    b = np.array([bool(rows_b[s][metric]) for s in seeds])
    only_a, only_b = int((a & ~b).sum()), int((b & ~a).sum())
    p = binomtest(only_a, only_a + only_b, 0.5).pvalue if only_a + only_b else 1.0
    return len(seeds), float(a.mean()), float(b.mean()), only_a, only_b, float(p)


def compare(run_a: str | Path, run_b: str | Path | None = None, planners: list[str] | None = None,
            against: str | None = None, metric: str = "success") -> list[Paired]:
    """Every (planner, N) evaluated in both folders, or the `planners` named; with `against`, each of
    `planners` in A against that planner in B (B defaults to A: two planners on the same tasks)."""
    if metric not in METRICS:
        raise ValueError(f"--metric {metric}: use one of {', '.join(METRICS)}")
    if against and not planners:
        raise ValueError("--against needs --planner (the planner of A to compare with it)")
    if run_b is None and not against:
        raise ValueError("one folder compares two of its planners: add --planner P --against Q, or a second folder")
    files_a = episode_files(run_a)
    files_b = files_a if run_b is None or str(run_b) == str(run_a) else episode_files(run_b)
    have_a = sorted({p for p, _ in files_a})
    for p in planners or []:
        if p not in have_a:
            raise ValueError(f"--planner {p}: not evaluated in {run_a} (it has {', '.join(have_a)})")
    out = []
    for (p, n), rows_a in sorted(files_a.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        if planners and p not in planners:
            continue
        q = against or p
        if (q, n) not in files_b:
            continue
        tasks, ra, rb, oa, ob, pv = pair(rows_a, files_b[(q, n)], metric)
        out.append(Paired(p, q, n, tasks, ra, rb, oa, ob, pv))
    if not out:
        raise ValueError(f"nothing to compare: no (planner, team size) of {run_a} is evaluated in "
                         f"{run_b or run_a}{' as ' + against if against else ''}")
    return out


def format_table(rows: list[Paired], metric: str = "success") -> str:
    head = (f"{'planner A':<24} {'planner B':<24} {'N':>3} {'tasks':>5} {metric + ' A':>10} {metric + ' B':>10} "
            f"{'B - A':>7} {'only A':>6} {'only B':>6} {'p':>7}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r.planner_a:<24} {r.planner_b:<24} {r.robots:>3} {r.tasks:>5} {r.rate_a:>10.3f} "
                     f"{r.rate_b:>10.3f} {r.rate_b - r.rate_a:>+7.3f} {r.only_a:>6} {r.only_b:>6} {r.p_value:>7.3f}")
    return "\n".join(lines)
