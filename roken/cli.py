"""`roken` command line: `roken plot RUN_DIR --episode ID --out FILE.png`, `roken animate RUN_DIR --index 0
--out FILE.gif`, `roken validate RUN_DIR`, `roken export RUN_OR_CHECKPOINT OUT`, `roken compare EVAL_A EVAL_B`, `roken quickstart`."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .config import ConfigError


def cmd_plot(args) -> int:
    from .data.store import read_run
    from .eval.plot import plot_episode
    from .world.metrics import failure_reason
    from .world.tasks import TaskConfig

    maps, episodes = read_run(args.run)
    if args.episode:
        chosen = [e for e in episodes if e["episode_id"] == args.episode]
        if not chosen:
            ids = ", ".join(e["episode_id"] for e in episodes[:5])
            print(f"error: no episode {args.episode!r} in {args.run} (for example: {ids})", file=sys.stderr)
            return 2
    else:
        if not 0 <= args.index < len(episodes):
            print(f"error: --index {args.index}: {args.run} holds {len(episodes)} episodes; use 0..{len(episodes) - 1} "
                  f"or --episode ID", file=sys.stderr)
            return 2
        chosen = [episodes[args.index]]
    e = chosen[0]
    if not 1 <= args.instants <= len(e["positions"]):
        print(f"error: --instants {args.instants}: use 1..{len(e['positions'])} (the episode's steps + 1)",
              file=sys.stderr)
        return 2
    gm = maps[e["map_id"]]
    why = "" if e["success"] else "\nfailed: " + (failure_reason(e["positions"], gm, e["goal"], e["leader"],
                                                                  TaskConfig()) or "?")
    title = (f"{e['episode_id']}\nsuccess={e['success']} reach={e['reach']} obs-coll={e['obstacle_collision']} "
             f"inter-coll={e['inter_collision']} connected={e['connectivity']}{why}")
    out = plot_episode(maps[e["map_id"]].occupancy, e["positions"], e["goal"], e["leader"], args.out,
                       instants=args.instants, title=title, crop=not args.full)
    print(out)
    return 0


def cmd_animate(args) -> int:
    import numpy as np

    from .data.store import read_run
    from .eval.plot import animate_episode

    maps, episodes = read_run(args.run)
    chosen = [e for e in episodes if e["episode_id"] == args.episode] if args.episode else \
        (episodes[args.index:args.index + 1] if 0 <= args.index < len(episodes) else [])
    if not chosen:
        print(f"error: no episode {args.episode or args.index!r} in {args.run} ({len(episodes)} episodes; "
              f"e.g. {episodes[0]['episode_id'] if episodes else '-'})", file=sys.stderr)
        return 2
    e = chosen[0]
    plans = None
    if e.get("plans") is not None and e.get("plan_steps"):
        N, P = e["num_robots"], len(e["plan_steps"])
        plans = np.asarray(e["plans"], np.float32).reshape(P, N, -1, 2)
    title = f"{e['episode_id']}  success={e['success']}"
    print(animate_episode(maps[e["map_id"]].occupancy, e["positions"], e["goal"], e["leader"], args.out, plans,
                          e.get("plan_steps"), every=args.every, title=title))
    return 0


def cmd_validate(args) -> int:
    from .data.store import check_manifest, read_run

    maps, episodes = read_run(args.run)
    print(f"{args.run}: {len(maps)} maps, {len(episodes)} episodes, schema ok, {check_manifest(args.run, episodes)}")
    return 0


def cmd_export(args) -> int:
    from .train.export import export

    if args.notes and not Path(args.notes).is_file():
        raise ValueError(f"--notes {args.notes}: no such file (a Markdown file appended to the model card)")
    notes = Path(args.notes).read_text() if args.notes else ""
    print(export(args.source, args.out, args.which, notes))
    return 0


def cmd_compare(args) -> int:
    from .eval.compare import compare, format_table

    planners = [p for p in (args.planner or "").split(",") if p] or None
    rows = compare(args.a, args.b, planners, args.against, args.metric)
    print(format_table(rows, args.metric))
    print("only A / only B: tasks one solves and the other does not; p: exact two-sided sign test on them")
    return 0


def cmd_train_gnn(args) -> int:
    from .config import load_config
    from .expert.gnn import train_scorer

    if min(args.tasks, args.states, args.steps, args.robots) < 1:
        raise ValueError("--tasks, --states, --steps and --robots must be >= 1")
    cfg = load_config(args.config, [f"eval.robots=[{args.robots}]"] + args.set)
    s = train_scorer(cfg, args.out, args.tasks, args.states, args.steps, seed=args.seed)
    print(f"{'graphs':>8} {'good':>6} {'train acc':>10} {'held-out acc':>13} {'seconds':>8}")
    print(f"{s['graphs']:>8} {s['good_fraction']:>6.2f} {s['train_accuracy']:>10.4f} {s['heldout_accuracy']:>13.4f} "
          f"{s['seconds']:>8.0f}")
    return 0


def cmd_quickstart(rest: list[str]) -> int:
    """Runs pipelines/quickstart.py of this checkout (the pipelines are not part of the installed package)."""
    import subprocess

    script = Path(__file__).resolve().parents[1] / "pipelines" / "quickstart.py"
    if not script.is_file():
        print("error: roken quickstart runs from a clone of the repository (pipelines/quickstart.py not found "
              "next to the installed package); git clone it and pip install -e .", file=sys.stderr)
        return 2
    return subprocess.call([sys.executable, str(script)] + rest)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["quickstart"]:
        return cmd_quickstart(argv[1:])
    ap = argparse.ArgumentParser(prog="roken", description=__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("quickstart", help="the main job on embedded defaults: generate, pretrain briefly, evaluate, "
                                      "report (roken quickstart --help)")
    p = sub.add_parser("plot", help="draw one episode of a dataset / evaluation folder as a PNG")
    p.add_argument("run", help="folder with maps/ and episodes/")
    p.add_argument("--episode", help="episode_id (default: --index)")
    p.add_argument("--index", type=int, default=0, help="episode number in file order")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--instants", type=int, default=4, help="instants at which communication edges are drawn")
    p.add_argument("--full", action="store_true", help="draw the whole map instead of the team's area")
    p.set_defaults(fn=cmd_plot)
    a = sub.add_parser("animate", help="animated GIF of an episode (Roken episodes: with each re-plan's chunk)")
    a.add_argument("run", help="folder with maps/ and episodes/")
    a.add_argument("--episode", help="episode_id (default: --index)")
    a.add_argument("--index", type=int, default=0, help="episode number in file order")
    a.add_argument("--every", type=int, default=4, help="simulator steps per frame")
    a.add_argument("--out", required=True, help="GIF to write")
    a.set_defaults(fn=cmd_animate)
    v = sub.add_parser("validate", help="check a folder against the episode-store contract")
    v.add_argument("run")
    v.set_defaults(fn=cmd_validate)
    x = sub.add_parser("export", help="ship a checkpoint: fp16 EMA weights, config.json and a model card")
    x.add_argument("source", help="checkpoint directory or run folder")
    x.add_argument("out", help="folder to write (replaced if it holds a checkpoint)")
    x.add_argument("--which", choices=("latest", "best"), default="latest", help="checkpoint of a run folder")
    x.add_argument("--notes", help="a Markdown file appended to the model card")
    x.set_defaults(fn=cmd_export)
    c = sub.add_parser("compare", help="paired comparison of two evaluations on the same tasks (sign test)")
    c.add_argument("a", help="evaluation folder A (episodes/ written by pipelines/evaluate.py)")
    c.add_argument("b", nargs="?", help="evaluation folder B (default: A, with --against)")
    c.add_argument("--planner", help="planners of A to compare, comma-separated (default: all in both)")
    c.add_argument("--against", help="the planner of B each one is compared with (default: the same planner)")
    c.add_argument("--metric", default="success", choices=("success", "reach"), help="the per-task outcome compared")
    c.set_defaults(fn=cmd_compare)
    g = sub.add_parser("train-gnn", help="train the GNN baseline's graph scorer on simulator labels (CPU, minutes)")
    g.add_argument("--out", default="models/gnn-scorer", help="folder for model.safetensors, config.json")
    g.add_argument("--tasks", type=int, default=256, help="expert episodes on train maps the graphs come from")
    g.add_argument("--states", type=int, default=8, help="states sampled per episode")
    g.add_argument("--steps", type=int, default=3000)
    g.add_argument("--robots", type=int, default=4, help="team size of the training graphs")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--config", help="YAML config file (task, sgg and gnn sections)")
    g.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    g.set_defaults(fn=cmd_train_gnn)
    args = ap.parse_args(argv)
    if getattr(args, "every", 1) < 1:
        print(f"error: --every {args.every}: must be >= 1 (simulator steps per frame)", file=sys.stderr)
        return 2
    try:
        return args.fn(args)
    except (ConfigError, ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
