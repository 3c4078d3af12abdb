"""Ablations judged the way users judge a planner: each variant (a named set of `--set` overrides) is trained
for the same budget (training seconds or optimizer steps) and scored in closed loop on the same `val` tasks.

    variants.yaml:   variants:
                       - {name: baseline, set: []}
                       - {name: sdf-off, set: ["loss.sdf_mode=off"]}

A variant is one work unit (roken.units): its run folder is OUT/variants/NAME (a Pretraining run, so an
interrupted variant resumes from its last checkpoint), and its result OUT/variants/NAME/result.json is written
last, atomically: a re-run skips variants whose result matches their overrides and budget. The closed-loop
figures are those of the run's final closed-loop validation (train.closed_loop_tasks tasks, the planner's
defaults); the learning curve is every closed-loop validation of the run against its training time.
"""
from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import torch
import yaml

from ..data.store import atomic_write_json

RESULT_KEYS = ("success", "reach", "obstacle_collision", "inter_collision", "connectivity")
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}$")


def load_variants(path: str | Path) -> list[dict]:
    """[{name, overrides}] from a variants file; every problem is named with the file and the fix."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"--variants {p}: no such file; see configs/ablate/ for examples")
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise ValueError(f"--variants {p}: not valid YAML ({e})") from None
    items = doc.get("variants") if isinstance(doc, dict) else None
    if not isinstance(items, list) or not items:
        raise ValueError(f"--variants {p}: expected a top-level `variants:` list of {{name: ..., set: [...]}}")
    out, seen = [], set()
    for i, v in enumerate(items):
        if not isinstance(v, dict) or "name" not in v:
            raise ValueError(f"--variants {p}: entry {i} needs a `name` (and a `set` list of key=value overrides)")
        name, sets = str(v["name"]), v.get("set") or []
        if not NAME.match(name) or name in seen:
            raise ValueError(f"--variants {p}: variant name {name!r} must be unique, letters, digits, _ . + -")
        if not isinstance(sets, list) or any(not isinstance(s, str) or "=" not in s for s in sets):
            raise ValueError(f"--variants {p}: variant {name!r}: `set` must be a list of 'key=value' strings")
        seen.add(name)
        out.append({"name": name, "overrides": list(sets)})
    return out


def budget_overrides(minutes: float | None, steps: int | None, episodes: int) -> list[str]:
    """The budget every variant gets: training minutes (train.time_budget_s; steps unbounded) or steps."""
    sets = [f"train.closed_loop_tasks={episodes}"]
    if minutes:
        sets += [f"train.time_budget_s={minutes * 60:g}", "train.steps=100000000"]
    if steps:
        sets += [f"train.steps={steps}"]
    return sets


def fingerprint(overrides: list[str], config_text: str = "") -> str:
    """What a variant's result depends on: its overrides and the base config file's text."""
    return hashlib.sha256(json.dumps([overrides, config_text]).encode()).hexdigest()[:16]


def config_text(config: str | None) -> str:
    return Path(config).read_text() if config else ""


def result_path(out: str | Path, name: str) -> Path:
    return Path(out) / "variants" / name / "result.json"


def finished(out: str | Path, name: str, overrides: list[str], config: str | None = None) -> dict | None:
    p = result_path(out, name)
    try:
        r = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return r if r.get("fingerprint") == fingerprint(overrides, config_text(config)) else None


def curve(run_dir: str | Path) -> list[dict]:
    """Closed-loop validations of a run: [{step, train_s, success, reach}], in step order."""
    rows, train_s = [], 0.0
    p = Path(run_dir) / "metrics.jsonl"
    for line in (p.read_text().splitlines() if p.is_file() else []):
        r = json.loads(line)
        train_s = r.get("time/train_s", train_s)
        if "closed_loop/success" in r:
            rows.append({"step": r["step"], "train_s": train_s, "success": r["closed_loop/success"],
                         "reach": r["closed_loop/reach"]})
    return rows


def run_variant(ctx: dict, payload: dict, cache: dict) -> dict:
    """Worker function: train one variant for the budget, return (and write) its result row."""
    from ..config import load_config
    from .loop import Pretraining, PretrainSpec

    name, overrides = payload["name"], payload["overrides"]
    done = finished(ctx["out"], name, overrides, ctx.get("config"))
    if done is not None:
        return done
    if ctx.get("threads"):
        torch.set_num_threads(int(ctx["threads"]))
    cfg = load_config(ctx.get("config"), overrides)
    run_dir = Path(ctx["out"]) / "variants" / name
    summary = Pretraining(PretrainSpec.of(cfg), ctx["data"], run_dir, ctx.get("val_data")).fit()
    v = summary.get("validation", {})
    row = {"name": name, "overrides": payload["variant_overrides"], "steps": summary["steps"],
           "cpu_seconds": summary["train_s"] * torch.get_num_threads(), "train_seconds": summary["train_s"],
           "threads": torch.get_num_threads(), "noise_draws": cfg.train.noise_draws,
           "draws": summary["steps"] * cfg.train.batch_size * cfg.train.noise_draws}
    row |= {k: v.get(f"closed_loop/{k}") for k in RESULT_KEYS}
    row |= {"first_move_cos_follower": v.get("val/first_move_cos_follower"),
            "first_move_cos_leader": v.get("val/first_move_cos_leader"), "l2_executed_m": v.get("val/l2_executed_m"),
            "episodes": v.get("closed_loop/episodes"), "curve": curve(run_dir),
            "fingerprint": fingerprint(overrides, config_text(ctx.get("config")))}
    atomic_write_json(row, result_path(ctx["out"], name))
    return row


def table(rows: list[dict]) -> str:
    head = ("| variant | overrides | steps | CPU min | success | reach | obs-coll | inter-coll | connected | "
            "first-move cos (follower) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")

    def f(x, d=3):
        return "n/a" if x is None else f"{x:.{d}f}"
    lines = [head] + [f"| {r['name']} | {' '.join(r['overrides']) or '(none)'} | {r['steps']} | "
                      f"{r['cpu_seconds'] / 60:.1f} | {f(r['success'])} | {f(r['reach'])} | "
                      f"{f(r['obstacle_collision'])} | {f(r['inter_collision'])} | {f(r['connectivity'])} | "
                      f"{f(r['first_move_cos_follower'])} |" for r in rows]
    return "\n".join(lines)


def write_report(out: str | Path, rows: list[dict], header: str = "") -> None:
    """OUT/ablation.json, OUT/ablation.md and OUT/ablation.png (closed-loop success vs CPU minutes)."""
    out = Path(out)
    atomic_write_json({"variants": rows}, out / "ablation.json")
    md = (f"# Ablation\n\n{header}\n\n" if header else "# Ablation\n\n") + table(rows) + "\n"
    tmp = out / ".ablation.md.tmp"
    tmp.write_text(md)
    tmp.replace(out / "ablation.md")
    plot_curves([(r["name"], r.get("curve") or [], r.get("threads", 1)) for r in rows], out / "ablation.png")


def plot_curves(lines: list[tuple[str, list[dict], int]], path: str | Path, keys=("success",)) -> None:
    """Closed-loop figures (curve() points) vs CPU minutes of training (train_s x threads), one line per run and
    key; written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, ax = plt.subplots(figsize=(6.4, 4))
    for label, c, threads in lines:
        for key in keys:
            ax.plot([p["train_s"] * threads / 60 for p in c], [p[key] for p in c], marker="o",
                    label=label if len(keys) == 1 else f"{label}: {key}")
    ax.set_xlabel("CPU minutes of training")
    ax.set_ylabel("closed loop on val tasks" if len(keys) > 1 else f"closed-loop {keys[0]} (val tasks)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
