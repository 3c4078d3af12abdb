"""The paper's figures for one checkpoint: scalability (N = 1..10, direct and clustered; the expert and the SGG
and GNN baselines beside it), replanning frequency
(replan every 1, 2, 4, 8 chunk moves) and sensing range (whole map, 20, 10, 5 m). Each setting is an ordinary
evaluation (roken.eval.harness) in its own folder under OUT/<sweep>/<setting>/, so a sweep resumes setting by
setting and every episode can be plotted; the tables go to OUT/<sweep>.json and .md, the figures to .png.
`rows` are the Roken rows each setting evaluates (plain `roken`, the paper's planner, by default; a deployable
row such as `roken+guided+geodesic` beside it), all on the same tasks.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from ..configtools import to_dict, with_overrides
from ..data import fs
from ..data.store import atomic_write_json
from .harness import evaluate
from .metrics import METRIC_KEYS

SWEEPS = ("scalability", "replanning", "sensing")


def check_rows(rows: tuple[str, ...]) -> None:
    """The Roken rows of a sweep (--planners), refused before anything runs when one is not a Roken row."""
    bad = [r for r in rows if r != "roken" and not r.startswith("roken+")]
    if not rows or bad:
        raise ValueError(f"--planners {','.join(rows)}: Roken rows only (roken, roken+safe, roken+guided+geodesic, ..)")


def settings(name: str, max_robots: int, rows: tuple[str, ...] = ("roken",)) -> list[tuple[str, float, dict]]:
    """(label, x value, overrides) of a sweep's settings; `rows`: the Roken planner rows of every setting."""
    check_rows(rows)
    roken = ",".join(rows)
    if name == "scalability":
        direct = [(f"direct N={n}", n, {"eval.robots": [n], "plan.cluster_size": 0,
                                         "eval.planner": "laplacian,sgg,gnn," + roken})
                  for n in range(1, min(10, max_robots) + 1)]
        clustered = [(f"clustered N={n}", n, {"eval.robots": [n], "plan.cluster_size": 4, "eval.planner": roken})
                     for n in range(5, 11)]
        return direct + clustered
    if name == "replanning":
        return [(f"replan every {k}", k, {"plan.replan_every": k, "eval.planner": roken}) for k in (1, 2, 4, 8)]
    if name == "sensing":
        return [(("whole map" if r == 0 else f"sensing {r:g} m"), r, {"plan.sensing_range": float(r),
                                                                     "eval.planner": roken}) for r in (0, 20, 10, 5)]
    raise ValueError(f"--sweeps: unknown sweep {name!r}; choose from {', '.join(SWEEPS)}")


def line_name(sweep: str, label: str, planner: str) -> str:
    """The plotted line of a row: the planner, and for a Roken row of the scalability sweep its rollout mode
    (plain `roken` keeps the bare mode name, as in the paper's figure)."""
    if sweep != "scalability" or not planner.startswith("roken"):
        return planner
    mode = label.split()[0]
    return mode if planner == "roken" else f"{planner} {mode}"


def run_sweep(cfg, name: str, out: str, max_robots: int, runner=None, planners: tuple[str, ...] = ("roken",)
              ) -> list[dict]:
    rows = []
    for label, x, ov in settings(name, max_robots, planners):
        slug = label.replace(" ", "-").replace("=", "")
        print(f"== {name}: {label}", file=sys.stderr, flush=True)
        m = evaluate(with_overrides(cfg, ov), fs.join(out, name, slug), runner)
        for planner, summary in m["planners"].items():
            rows.append({"sweep": name, "setting": label, "x": x, "planner": line_name(name, label, planner)} |
                        {k: summary[k] for k in METRIC_KEYS + ("episodes",)})
    atomic_write_json({"sweep": name, "rows": rows, "config": to_dict(cfg)}, fs.join(out, f"{name}.json"))
    Path(out, f"{name}.md").write_text(markdown(name, rows))
    plot(name, rows, Path(out, f"{name}.png"))
    return rows


def markdown(name: str, rows: list[dict]) -> str:
    head = "| setting | planner | episodes | full success | obs. coll. | inter coll. | connected | reach | length |"
    lines = [f"### {name}", "", head, "|" + "---|" * 9]
    for r in rows:
        lines.append(f"| {r['setting']} | {r['planner']} | {r['episodes']} | {r['full_success']:.3f} | "
                     f"{r['obstacle_collision']:.3f} | {r['inter_collision']:.3f} | {r['connectivity']:.3f} | "
                     f"{r['reach']:.3f} | {_num(r['length'])} |")
    return "\n".join(lines) + "\n"


def _num(x) -> str:
    """A table figure; '-' where there is none (NaN in memory, null once a metrics.json is read back)."""
    return "-" if x is None or x != x else f"{x:.3f}"


def plot(name: str, rows: list[dict], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), dpi=110)
    xlabel = {"scalability": "robots N", "replanning": "chunk moves executed per re-plan",
              "sensing": "sensing range (m, 0 = whole map)"}[name]
    for ax, key in zip(axes, ("full_success", "reach")):
        for planner in dict.fromkeys(r["planner"] for r in rows):
            pts = sorted((r["x"], r[key]) for r in rows if r["planner"] == planner)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=planner)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(key.replace("_", " "))
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{name} sweep")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out
