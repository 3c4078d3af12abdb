"""The main job in one command, on embedded defaults: generate a small dataset, pretrain briefly, evaluate
the shipped model (the paper's planner and the deployable one, configs/deploy.yaml) and the one just trained
beside the expert on the same tasks, and write a short report.

    python pipelines/quickstart.py --out runs/quickstart            # a private Ray cluster on this machine
    roken quickstart --out runs/quickstart                          # the same
    python pipelines/quickstart.py --out runs/qs --workers 0        # everything in this process, no Ray

About 4 minutes on 2 cores. Every stage is an ordinary pipeline run (generate.py, pretrain.py, evaluate.py)
with its progress shown; re-running the command resumes or reuses what is done. OUT/report.md holds the
tables and links the figures (OUT/rows.png, an episode PNG and GIF).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "roken-cpu-four-dagger"  # the CPU recipe + DAgger, 4 robots (README "The shipped models")
DEPLOY = ROOT / "configs" / "deploy.yaml"  # the deployable planner's settings (README "Planning with Roken")
ROW = "roken+guided+geodesic"  # its row: guided sampling, verified candidates ranked by free-space progress


def stage(title: str, script: str, args: list[str], where: list[str]) -> float:
    print(f"\n=== {title}\n$ python pipelines/{script} {' '.join(args + where)}", flush=True)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, str(ROOT / "pipelines" / script)] + args + where, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"quickstart: {script} failed (exit {r.returncode}); fix the error above and re-run "
                         f"the same command (finished stages are reused)")
    return time.perf_counter() - t0


def bar_chart(rows: list[tuple[str, dict]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    keys = ("full_success", "reach", "obstacle_collision", "inter_collision", "connectivity")
    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=110)
    w = 0.8 / len(rows)
    for k, (name, m) in enumerate(rows):
        ax.bar(np.arange(len(keys)) + k * w, [m[key] for key in keys], w, label=name)
    ax.set_xticks(np.arange(len(keys)) + 0.4 - w / 2, [k.replace("_", " ") for k in keys])
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=8)
    ax.set_title("same tasks, 4 robots, unseen maps")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/quickstart", help="folder for everything (default runs/quickstart)")
    ap.add_argument("--episodes", type=int, default=24, help="evaluation tasks (4 robots)")
    ap.add_argument("--steps", type=int, default=200, help="pretraining steps of the brief run")
    ap.add_argument("--workers", type=int, help="0 = in-process, no Ray (default: a private --local cluster)")
    a = ap.parse_args(argv)
    out = Path(a.out).resolve()
    if out.exists() and not out.is_dir():
        print(f"error: --out {a.out}: is a file; the quickstart writes a folder there", file=sys.stderr)
        return 2
    marker = out / ".quickstart.json"
    settings = {"episodes": a.episodes, "steps": a.steps, "shipped": str(SHIPPED.relative_to(ROOT))}
    if out.is_dir() and any(out.iterdir()):
        try:
            mine = json.loads(marker.read_text())
        except (OSError, ValueError):
            mine = None
        if mine is None:
            print(f"error: --out {a.out}: the folder holds files the quickstart did not make "
                  f"({', '.join(sorted(p.name for p in out.iterdir())[:5])}); choose a new or empty folder",
                  file=sys.stderr)
            return 2
        if mine.get("settings") != settings:
            print(f"error: --out {a.out}: a quickstart with other settings ({mine.get('settings')}) is there; "
                  f"choose a new folder or the same settings", file=sys.stderr)
            return 2
        if mine.get("complete") and (out / "report.md").is_file():  # finished: reuse everything, rewrite nothing
            print((out / "report.md").read_text())
            print(f"report: {out / 'report.md'} (finished earlier; nothing was rerun)")
            return 0
    out.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"settings": settings, "complete": False}))
    where = ["--workers", "0"] if a.workers == 0 else ["--local"]
    t = {}
    t["generate"] = stage("1/4 expert dataset: 24 training maps x 4 episodes", "generate.py",
                          ["--maps", "train", "--num-maps", "24", "--episodes-per-map", "4", "--out", str(out / "data")],
                          where)
    t["pretrain"] = stage(f"2/4 brief pretraining: small model, {a.steps} steps (a real run: configs/pretrain/)",
                          "pretrain.py", ["--data", str(out / "data"), "--out", str(out / "pretrain"), "--config",
                                          str(ROOT / "configs" / "pretrain" / "laptop.yaml"), "--steps", str(a.steps),
                                          "--batch-size", "16", "--set", "train.eval_every=100",
                                          "--set", "train.checkpoint_every=100", "--set", "train.val_prompts=8"],
                          where if a.workers == 0 else ["--local", "--workers", "1"])
    common = ["--robots", "4", "--episodes", str(a.episodes), "--maps", "eval", "--config", str(DEPLOY)]
    t["evaluate shipped"] = stage("3/4 the shipped model beside the expert (same tasks): the paper's planner and the "
                                  "deployable one", "evaluate.py",
                                  ["--planner", f"laplacian,roken,{ROW}", "--checkpoint", str(SHIPPED),
                                   "--out", str(out / "eval-shipped")] + common, where)
    t["evaluate brief"] = stage("4/4 the model just trained (same tasks)", "evaluate.py",
                                ["--planner", "roken", "--checkpoint", str(out / "pretrain"),
                                 "--out", str(out / "eval-brief")] + common, where)
    shipped = json.loads((out / "eval-shipped" / "metrics.json").read_text())["planners"]
    brief = json.loads((out / "eval-brief" / "metrics.json").read_text())["planners"]["roken"]
    rows = [("expert (laplacian)", shipped["laplacian"]), ("roken: shipped", shipped["roken"]),
            (f"{ROW} (configs/deploy.yaml): shipped", shipped[ROW]), (f"roken: brief {a.steps} steps", brief)]
    bar_chart(rows, out / "rows.png")
    figs = []
    for tool, name in (("plot", "episode.png"), ("animate", "episode.gif")):
        r = subprocess.run([sys.executable, "-m", "roken", tool, str(out / "eval-shipped"), "--episode",
                            f"{ROW}-n04-e00000-" + _first_map(out), "--out", str(out / name)], cwd=ROOT,
                           capture_output=True, text=True)
        if r.returncode == 0:
            figs.append(name)
    head = "| planner | episodes | full success | obs. coll. | inter coll. | connected | reach | length |"
    lines = ["# Roken quickstart", "", f"Tasks: {a.episodes} x 4 robots on unseen generated maps, the same for "
             f"every row. Shipped model: `{SHIPPED.relative_to(ROOT)}`, plain (`roken`, the paper's planner) and "
             f"deployable (`{ROW}` with `{DEPLOY.relative_to(ROOT)}`; the episode figures are its first task); "
             f"brief run: `{out / 'pretrain'}`.", "",
             head, "|" + "---|" * 8]
    for name, m in rows:
        length = "-" if m["length"] is None or m["length"] != m["length"] else f"{m['length']:.3f}"
        lines.append(f"| {name} | {m['episodes']} | {m['full_success']:.3f} | {m['obstacle_collision']:.3f} | "
                     f"{m['inter_collision']:.3f} | {m['connectivity']:.3f} | {m['reach']:.3f} | {length} |")
    lines += ["", "![rows](rows.png)"] + [f"![{f}]({f})" for f in figs]
    lines += ["", "| stage | seconds |", "|---|---|"] + [f"| {k} | {v:.0f} |" for k, v in t.items()]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    marker.write_text(json.dumps({"settings": settings, "complete": True}))
    print("\n" + "\n".join(lines[4:4 + 2 + len(rows)]))
    print(f"\nreport: {out / 'report.md'}  (total {sum(t.values()) / 60:.1f} min)")
    return 0


def _first_map(out: Path) -> str:
    import pyarrow.parquet as pq

    ids = pq.read_table(out / "eval-shipped" / "episodes" / "roken-n04.parquet", columns=["map_id"]).column(0)
    return str(ids[0])


if __name__ == "__main__":
    sys.exit(main())
