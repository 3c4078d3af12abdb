"""Aggregate metrics over episodes and the paper-style table; per-episode scoring is `roken.world.metrics`."""
from __future__ import annotations

import numpy as np

from ..world.metrics import EpisodeMetrics, episode_metrics  # noqa: F401  (re-exported for callers)

METRIC_KEYS = ("full_success", "obstacle_collision", "inter_collision", "connectivity", "reach", "length")


def summarize(rows: list[EpisodeMetrics] | list[dict]) -> dict:
    """Mean of each metric over episodes; `length` over full-success episodes only (nan if none)."""
    def get(r, k):
        return r[k] if isinstance(r, dict) else getattr(r, k)

    n = len(rows)
    if n == 0:
        return {k: float("nan") for k in METRIC_KEYS} | {"episodes": 0}
    succ = np.array([get(r, "success") for r in rows], dtype=bool)
    ratios = np.array([get(r, "path_length") / get(r, "astar_length") if get(r, "astar_length") > 0
                       else np.nan for r in rows])
    return {
        "full_success": float(succ.mean()),
        "obstacle_collision": float(np.mean([get(r, "obstacle_collision") for r in rows])),
        "inter_collision": float(np.mean([get(r, "inter_collision") for r in rows])),
        "connectivity": float(np.mean([get(r, "connectivity") for r in rows])),
        "reach": float(np.mean([get(r, "reach") for r in rows])),
        "length": float(np.nanmean(ratios[succ])) if succ.any() else float("nan"),
        "episodes": n,
    }


def format_table(rows: list[tuple[str, dict]]) -> str:
    """Paper-style table: one row per (label, summary)."""
    head = f"{'planner':<22}{'N':>4}{'episodes':>10}{'full succ':>11}{'obs-coll':>10}{'inter-coll':>12}" \
           f"{'connect':>9}{'reach':>8}{'length':>8}"
    lines = [head, "-" * len(head)]
    for label, m in rows:
        name, _, n = label.rpartition("@")
        lines.append(f"{name:<22}{n:>4}{m['episodes']:>10d}{m['full_success']:>11.3f}"
                     f"{m['obstacle_collision']:>10.3f}{m['inter_collision']:>12.3f}{m['connectivity']:>9.3f}"
                     f"{m['reach']:>8.3f}{m['length']:>8.3f}")
    return "\n".join(lines)


# The benchmarks' compact columns of a summary (full success, reach, the three constraint rates), one header and
# one formatter so every benchmark table lines up the same way.
COMPACT_HEAD = f"{'success':>9}{'reach':>7}{'obs.':>7}{'inter':>7}{'conn.':>7}"


def compact_cells(m: dict) -> str:
    """COMPACT_HEAD's cells of a summarize() result."""
    return (f"{m['full_success']:>9.3f}{m['reach']:>7.3f}{m['obstacle_collision']:>7.3f}{m['inter_collision']:>7.3f}"
            f"{m['connectivity']:>7.3f}")
