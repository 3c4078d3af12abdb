"""One evaluation harness for every planner: maps -> tasks -> planner -> episodes -> metrics.

Episode e of team size N runs on map e mod M with task seed (eval.seed, N, e): the same config always
gives the same tasks, so planners are compared on identical episodes. `eval.planner` is one planner or a
list (`laplacian,roken,roken+safe`): every planner runs the same tasks and the table has a row per planner.
Planners: `laplacian` (the expert), the baselines `sgg` and `gnn` (roken.expert.sgg / .gnn) and Roken from
`plan.checkpoint`, plain (`roken`, one candidate, the paper's) or with verified selection over plan.candidates
(`roken+safe`, `roken+geodesic`; roken.plan.select).
Output folder:
  maps/maps.parquet                               (the store contract, roken.data.store)
  episodes/n{N:02d}.parquet                       the expert's episodes
  episodes/{planner}-n{N:02d}.parquet             any other planner's ('+' written '-'), with its re-plans
  metrics.json                                    the first planner's metrics at the top level (as with one
                                                  planner), every planner's under `planners`, the config
A (planner, team size) whose episode file exists with the same config fingerprint is reused, and a killed run
keeps its finished units under episodes/_units/ until then (resume; roken.eval.folder).
"""
from __future__ import annotations

import hashlib
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..configtools import from_dict, to_dict
from ..data import fs
from ..data.store import atomic_write_json, atomic_write_table, episode_record, episodes_table, maps_table
from ..expert.laplacian import ExpertConfig, LaplacianExpert
from ..expert.gnn import GNNConfig
from ..expert.sgg import SGGConfig
from ..progress import Progress
from ..units import InProcessRunner, Unit
from ..world.grid import GridMap
from ..world.loaders import MapError, find_map_files, load_map_file
from ..world.maps import SPLITS, MapConfig, generate_map, split_size
from ..world.tasks import TaskConfig, TaskError, sample_task
from ..plan.controller import rollout_config, row_name
from ..plan.rollout import PlanConfig
from .folder import (episode_file, fingerprint, fingerprints, refuse_other_config, reuse, reuse_unit,  # noqa: F401
                     unit_file)
from .metrics import format_table, summarize

PLANNERS = ("laplacian", "sgg", "gnn", "roken", "roken+safe", "roken+geodesic", "roken+guided",
            "roken+guided+safe", "roken+guided+geodesic")


@dataclass
class EvalConfig:
    planner: str = "laplacian"  # one planner or a comma-separated list (PLANNERS)
    robots: list[int] = field(default_factory=lambda: [4])
    episodes: int = 200  # per team size
    maps: str = "eval"  # "train", "val", "eval", or a folder / glob / file of external maps
    num_maps: int | None = None  # at most this many maps (default: the whole split or every file)
    seed: int = 0
    unit_episodes: int = 100  # episodes per work unit (a unit is one batched expert run)


def load_maps(cfg) -> tuple[list[GridMap], list[dict]]:
    """The maps an evaluation runs on, and the files that could not be used (with the reason)."""
    ec = cfg.eval
    if ec.maps in SPLITS:
        n = split_size(cfg.map, ec.maps)
        n = min(n, ec.num_maps) if ec.num_maps else n
        n = min(n, max(ec.episodes, 1))  # maps beyond the episode count would never be used
        return [generate_map(cfg.map, ec.maps, i) for i in range(n)], []
    files = find_map_files(ec.maps)
    if ec.num_maps:
        files = files[:ec.num_maps]
    maps, bad = [], []
    for f in files:
        try:
            maps.append(load_map_file(f, cfg.map))
        except MapError as e:
            bad.append({"file": e.path, "reason": e.reason})
    seen: dict[str, int] = {}
    for m in maps:  # file stems may repeat across folders: keep ids unique
        k = seen.get(m.map_id, 0)
        seen[m.map_id] = k + 1
        if k:
            m.map_id = f"{m.map_id}-{k}"
    return maps, bad


def planner_names(ec: EvalConfig, pc: PlanConfig | None = None) -> list[str]:
    """The rows of an evaluation: `roken` with plan.select set is named for its selection (roken+safe)."""
    names = [p.strip() for p in str(ec.planner).split(",") if p.strip()]
    if pc is not None and (pc.select != "none" or pc.guide):
        names = [row_name(pc) if p == "roken" else p for p in names]
    return list(dict.fromkeys(names))


def uses_roken(ec: EvalConfig) -> bool:
    return any(p.startswith("roken") for p in planner_names(ec))


def check(ec: EvalConfig) -> None:
    """Flags and fields checked before anything is written, naming the flag and the valid range."""
    bad = [p for p in planner_names(ec) if p not in PLANNERS]
    if bad or not planner_names(ec):
        raise ValueError(f"--planner {ec.planner!r}: unknown {', '.join(bad) or '(empty)'}; available: "
                         f"{', '.join(PLANNERS)} (several: --planner laplacian,roken)")
    if not ec.robots or min(ec.robots) < 1:
        raise ValueError(f"--robots {','.join(map(str, ec.robots)) or '(empty)'}: team sizes must be >= 1, "
                         f"e.g. --robots 4 or --robots 2,4,8")
    if ec.episodes < 1:
        raise ValueError(f"--episodes {ec.episodes}: must be >= 1 (episodes per team size)")
    if ec.num_maps is not None and ec.num_maps < 1:
        raise ValueError(f"--num-maps {ec.num_maps}: must be >= 1; omit it to use every map")
    if ec.seed < 0:
        raise ValueError(f"--seed {ec.seed}: must be >= 0")
    if ec.unit_episodes < 1:
        raise ValueError(f"eval.unit_episodes={ec.unit_episodes}: must be >= 1")


def make_tasks(cfg, maps: list[GridMap], n: int):
    tasks, skipped = [], []
    for e in range(cfg.eval.episodes):
        gm = maps[e % len(maps)]
        rng = np.random.default_rng([cfg.eval.seed, n, e])
        try:
            tasks.append((e, sample_task(gm, n, cfg.task, rng, seed=e)))
        except TaskError as err:
            skipped.append({"episode": e, "map_id": gm.map_id, "reason": str(err)})
    return tasks, skipped


def run_planner(cfg, planner: str, tasks, maps_by_id, cache: dict, model_blob: dict | None = None,
                gnn_blob: dict | None = None):
    """Yield (index into tasks, positions (T+1, N, 2), extra columns) for one planner."""
    if planner == "laplacian":
        expert = LaplacianExpert(cfg.expert, cfg.task)
        for i, ep in expert.run([t for _, t in tasks], maps_by_id):
            yield i, ep.positions, {}
        return
    if planner in ("sgg", "gnn"):
        from ..expert.sgg import SGGPlanner

        if planner == "gnn":
            from ..expert.gnn import GNNPlanner, scorer_from_bytes

            if "gnn" not in cache:
                cache["gnn"] = scorer_from_bytes(gnn_blob)
            base = GNNPlanner(cfg.gnn, cfg.sgg, cfg.task, cfg.expert, cache["gnn"])
        else:
            base = SGGPlanner(cfg.sgg, cfg.task, cfg.expert)
        for i, pos, _ in base.run([t for _, t in tasks], maps_by_id):
            yield i, pos, {}
        return
    from ..plan import RokenPlanner, RokenRollout

    if "roken" not in cache:  # each worker unpacks the weights once
        cache["roken"] = RokenPlanner.unpack(model_blob, cfg.plan.device, cfg.plan.dtype)
    rollout = RokenRollout(cache["roken"], rollout_config(cfg.plan, planner), cfg.task, cfg.expert)
    for i, pos, info in rollout.run([t for _, t in tasks], maps_by_id):
        extra = {"holds": info["holds"]}
        if cfg.plan.record_plans:
            extra |= {"plan_steps": info["plan_steps"], "plans": info["plans"].reshape(-1)}
        yield i, pos, extra


@dataclass
class EvalSections:
    """The config sections an evaluation unit reads."""
    map: MapConfig = field(default_factory=MapConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    plan: PlanConfig = field(default_factory=PlanConfig)
    sgg: SGGConfig = field(default_factory=SGGConfig)
    gnn: GNNConfig = field(default_factory=GNNConfig)


SECTIONS = ("map", "task", "expert", "eval", "plan", "sgg", "gnn")


def eval_unit(ctx: dict, payload: dict, cache: dict) -> list[dict]:
    """Worker function (roken.units): plan and score one unit's episodes; returns their rows."""
    if "cfg" not in cache:
        cache["cfg"] = from_dict(EvalSections, {k: ctx["config"][k] for k in SECTIONS if k in ctx["config"]})
        cache["maps"] = {mid: GridMap(mid, occ, src) for mid, occ, src in ctx["maps"]}
    cfg, by_id = cache["cfg"], cache["maps"]
    n, tasks, planner = payload["n"], payload["tasks"], payload.get("planner", "laplacian")
    rows: list[dict | None] = [None] * len(tasks)
    tick = ctx.get("on_episode")  # in-process runs report every finished episode (progress), Ray runs per unit
    for i, pos, extra in run_planner(cfg, planner, tasks, by_id, cache, ctx.get("model"), ctx.get("gnn")):
        if tick is not None:
            tick()
        e, task = tasks[i]
        rows[i] = episode_record(f"{planner}-n{n:02d}-e{e:05d}-{task.map_id}", planner, task,
                                 by_id[task.map_id], pos, cfg.task, e) | extra
    return [r for r in rows if r is not None]


def load_model(cfg) -> tuple[dict | None, str]:
    """The Roken checkpoint of an evaluation packed as bytes (shipped to every worker once), and its id."""
    if not uses_roken(cfg.eval):
        return None, ""
    from ..plan.planner import RokenPlanner
    from ..plan.rollout import check as check_plan

    check_plan(cfg.plan)
    if not cfg.plan.checkpoint:
        raise ValueError("--planner roken needs --checkpoint PATH: a checkpoint directory or a run folder "
                         "(the shipped models: --checkpoint models/roken-cpu-four, models/roken-small-mixed)")
    blob = RokenPlanner.pack(cfg.plan.checkpoint, cfg.plan.which, cfg.task.max_step)
    planner = RokenPlanner.unpack(blob, "cpu")  # loaded once here: a bad checkpoint fails before any write
    check_plan(cfg.plan, planner)
    max_robots = blob["config"]["samples"]["max_robots"]
    if not cfg.plan.cluster_size and max(cfg.eval.robots) > max_robots:
        raise ValueError(f"--robots {max(cfg.eval.robots)}: the model plans at most {max_robots} robots in one "
                         f"call (samples.max_robots of {blob['path']}); add --cluster-size 4 (clustered rollout)")
    if cfg.plan.cluster_size > max_robots:
        raise ValueError(f"--cluster-size {cfg.plan.cluster_size}: the model has {max_robots} robot tokens")
    return blob, hashlib.sha256(blob["weights"]).hexdigest()[:16]


def evaluate(cfg, out: str | Path, runner=None, overwrite: bool = False) -> dict:
    """Run the evaluation described by `cfg` into folder or URI `out`; returns the metrics dict.

    Episodes are cut into units of `eval.unit_episodes` per planner and team size; `runner` (default:
    in-process) runs them, so --workers 0 and any number of Ray workers give identical episodes."""
    check(cfg.eval)
    out = str(out)
    blob, model_id = load_model(cfg)
    gnn_blob = None
    if "gnn" in planner_names(cfg.eval):
        from ..expert.gnn import scorer_bytes

        gnn_blob = scorer_bytes(cfg.gnn.checkpoint)  # read once here: a missing scorer fails before any write
    if not overwrite:
        refuse_other_config(out, cfg, model_id)
    planners = planner_names(cfg.eval, cfg.plan)
    weights_id = lambda p: gnn_blob["sha256"] if p == "gnn" else model_id  # noqa: E731  (the weights a row ran)
    runner = runner or InProcessRunner()
    t0 = time.perf_counter()
    maps, bad = load_maps(cfg)
    for b in bad:
        print(f"skipped map {b['file']}: {b['reason']}", file=sys.stderr)
    if not maps:
        raise MapError(cfg.eval.maps, "none of the maps could be used (reasons above)")
    atomic_write_table(maps_table(maps), fs.join(out, "maps", "maps.parquet"), "maps")
    done: dict[tuple[str, int], tuple[list, list]] = {}
    units, skipped_by_n, todo, resumed, unit_keys, fps = [], {}, [], {}, {}, {}
    k = cfg.eval.unit_episodes
    for n in cfg.eval.robots:
        tasks = None
        for p in planners:
            fps[(p, n)] = fingerprints(cfg, n, p, weights_id(p))  # [0]: the one files are written with
            reused = reuse(episode_file(out, p, n), fps[(p, n)], n)
            if reused is not None:
                done[(p, n)] = reused
                skipped_by_n.setdefault(n, reused[1])
                continue
            if tasks is None:  # sampled once per team size, only when some planner has to run them
                tasks, skipped_by_n[n] = make_tasks(cfg, maps, n)
                for s in skipped_by_n[n]:
                    print(f"[N={n}] skipped episode {s['episode']}: {s['reason']}", file=sys.stderr)
            todo.append((p, n))
            for j in range(0, len(tasks), k):
                unit = Unit(f"{p}-n{n:02d}-u{j // k:03d}", {"n": n, "planner": p, "tasks": tasks[j:j + k]},
                            size=len(tasks[j:j + k]))
                rows = reuse_unit(unit_file(out, unit.key), fps[(p, n)], [e for e, _ in unit.payload["tasks"]])
                unit_keys.setdefault((p, n), []).append(unit.key)
                if rows is None:
                    units.append(unit)
                else:
                    resumed.setdefault((p, n), []).extend(rows)
    for (p, n), rows in resumed.items():
        print(f"[N={n}] {p}: resuming {len(rows)} episodes of units finished earlier", file=sys.stderr)
    rows_by: dict[tuple[str, int], list] = {key: list(resumed.get(key, [])) for key in todo}
    failures = []
    ctx = {"config": to_dict(cfg), "maps": [(m.map_id, m.occupancy, m.source) for m in maps], "model": blob,
           "gnn": gnn_blob}
    bar = Progress(sum(u.size for u in units), f"[{','.join(planners)}]")
    # Progress per finished episode: in-process through ctx["on_episode"], on Ray by polling the actors' counts
    # (RayRunner.on_progress); what is shown never goes back and ends at the total when every unit is done.
    seen = {"ticks": 0, "units": 0, "shown": 0, "base": 0, "last": 0}

    def show() -> None:
        target = min(max(seen["ticks"], seen["units"]), bar.total)
        if target > seen["shown"]:
            bar.update(target - seen["shown"])
            seen["shown"] = target

    def tick() -> None:
        seen["ticks"] += 1
        show()

    def polled(total: int) -> None:  # actors' counters; one that restarted counts from 0 again
        if total < seen["last"]:
            seen["base"] += seen["last"]
        seen["last"] = total
        seen["ticks"] = seen["base"] + total
        show()
    if runner.workers == 0:
        ctx["on_episode"] = tick
    else:
        ctx["report_episodes"] = True
        runner.on_progress = polled
    try:
        for r in runner.imap_unordered("roken.eval.harness:eval_unit", ctx, units):
            key = (r.unit.payload["planner"], r.unit.payload["n"])
            if r.ok:
                rows_by[key] += r.value
                if r.value:  # kept until its team size's file is written: a killed run resumes from here
                    atomic_write_table(episodes_table(r.value), unit_file(out, r.unit.key), "episodes",
                                       {"fingerprint": fps[key][0],
                                        "episodes": [e for e, _ in r.unit.payload["tasks"]]})
            else:
                failures.append({"unit": r.unit.key, "planner": key[0], "team_size": key[1], "error": r.error})
            seen["units"] += r.unit.size
            show()
    finally:
        runner.shutdown()
    failed = {(f["planner"], f["team_size"]) for f in failures}
    for (p, n), rows in rows_by.items():
        rows.sort(key=lambda r: r["seed"])
        if (p, n) not in failed and rows:  # a file with a failed unit is not stored: a re-run redoes it
            atomic_write_table(episodes_table(rows), episode_file(out, p, n), "episodes",
                               {"fingerprint": fps[(p, n)][0], "skipped": skipped_by_n[n]})
            for key in unit_keys[(p, n)]:  # the units' files are in it now
                fs.remove(unit_file(out, key))
            fs.remove_empty_folder(fs.join(out, "episodes", "_units"))
        done[(p, n)] = (rows, skipped_by_n[n])
    by_planner, table_rows = {}, []
    for p in planners:
        per_n, all_rows, skipped_all = {}, [], {}
        for n in cfg.eval.robots:
            rows, skipped = done[(p, n)]
            summary = summarize(rows)
            per_n[str(n)] = summary | {"skipped": len(skipped)}
            skipped_all[str(n)] = skipped
            all_rows += rows
            table_rows.append((f"{p}@{n}", summary))
        if len(cfg.eval.robots) > 1:
            table_rows.append((f"{p}@all", summarize(all_rows)))
        by_planner[p] = summarize(all_rows) | {"by_team_size": per_n, "skipped_episodes": skipped_all}
    first = by_planner[planners[0]]
    metrics = first | {
        "planner": planners[0], "planners": by_planner, "model": {"path": blob["path"], "sha256": model_id}
        if blob else None, "bad_maps": bad, "failures": failures, "maps": len(maps),
        "seconds": round(time.perf_counter() - t0, 2), "workers": runner.workers, "config": to_dict(cfg),
    }
    atomic_write_json(metrics, fs.join(out, "metrics.json"))
    print(format_table(table_rows))
    if failures:
        print(f"{len(failures)} unit(s) failed: {failures}; re-run the same command to retry them",
              file=sys.stderr)
    return metrics
