"""One evaluation harness for every planner: maps -> tasks -> planner -> episodes -> metrics.

Episode e of team size N runs on map e mod M with task seed (eval.seed, N, e): the same config always
gives the same tasks, so planners are compared on identical episodes. Output folder:
  maps/maps.parquet, episodes/n{N:02d}.parquet   (the store contract, roken.data.store)
  metrics.json                                   (per team size and overall, with the resolved config)
A team size whose episode file already exists with the same config fingerprint is reused (resume).
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from ..configtools import to_dict
from ..data.store import (StoreError, atomic_write_json, atomic_write_table, episodes_table, maps_table,
                          read_episodes)
from ..expert.laplacian import LaplacianExpert
from ..progress import Progress
from ..world.grid import GridMap
from ..world.loaders import MapError, find_map_files, load_map_file
from ..world.maps import SPLITS, generate_map, split_size
from ..world.tasks import TaskError, sample_task
from .metrics import episode_metrics, format_table, summarize

PLANNERS = ("laplacian",)


@dataclass
class EvalConfig:
    planner: str = "laplacian"
    robots: list[int] = field(default_factory=lambda: [4])
    episodes: int = 200  # per team size
    maps: str = "eval"  # "train", "eval", or a folder / glob / file of external maps
    num_maps: int | None = None  # at most this many maps (default: the whole split or every file)
    seed: int = 0
    workers: int = 0  # 0: in-process, no Ray


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


def fingerprint(cfg, n: int) -> str:
    d = to_dict(cfg)
    d["eval"] = {k: v for k, v in d["eval"].items() if k not in ("robots", "workers")}
    return hashlib.sha256(json.dumps([d, n], sort_keys=True).encode()).hexdigest()[:16]


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


def run_planner(cfg, tasks, maps_by_id):
    """Yield (index into tasks, positions (T+1, N, 2)) for `cfg.eval.planner`."""
    if cfg.eval.planner == "laplacian":
        expert = LaplacianExpert(cfg.expert, cfg.task)
        for i, ep in expert.run([t for _, t in tasks], maps_by_id):
            yield i, ep.positions
    else:
        raise ValueError(f"unknown planner {cfg.eval.planner!r}; available: {', '.join(PLANNERS)}")


def evaluate_team_size(cfg, maps: list[GridMap], n: int, out: Path) -> tuple[list[dict], list[dict]]:
    path = out / "episodes" / f"n{n:02d}.parquet"
    fp = fingerprint(cfg, n)
    if path.exists():
        try:
            meta = pq.read_schema(path).metadata or {}
            if json.loads(meta.get(b"fingerprint", b'""')) == fp:
                print(f"[N={n}] reusing {path} (same config)")
                return read_episodes(path), json.loads(meta.get(b"skipped", b"[]"))
        except (StoreError, OSError, ValueError):
            pass
    by_id = {m.map_id: m for m in maps}
    tasks, skipped = make_tasks(cfg, maps, n)
    for s in skipped:
        print(f"[N={n}] skipped episode {s['episode']}: {s['reason']}")
    rows: list[dict | None] = [None] * len(tasks)
    bar = Progress(len(tasks), f"[{cfg.eval.planner} N={n}]")
    for i, pos in run_planner(cfg, tasks, by_id):
        e, task = tasks[i]
        gm = by_id[task.map_id]
        m = episode_metrics(pos, gm, task.goal, task.leader, cfg.task)
        rows[i] = {
            "episode_id": f"{cfg.eval.planner}-n{n:02d}-e{e:05d}-{task.map_id}", "map_id": task.map_id,
            "planner": cfg.eval.planner, "num_robots": n, "leader": task.leader, "num_steps": len(pos) - 1,
            "goal": task.goal, "positions": pos, "success": m.success, "reach": m.reach,
            "obstacle_collision": m.obstacle_collision, "inter_collision": m.inter_collision,
            "connectivity": m.connectivity, "path_length": m.path_length, "astar_length": m.astar_length,
            "seed": e,
        }
        bar.update()
    done = [r for r in rows if r is not None]
    if done:
        atomic_write_table(episodes_table(done), path, "episodes", {"fingerprint": fp, "skipped": skipped})
    return done, skipped


def evaluate(cfg, out: str | Path) -> dict:
    """Run the evaluation described by `cfg` into folder `out`; returns the metrics dict."""
    if cfg.eval.workers != 0:
        raise ValueError("eval.workers > 0 needs the Ray fan-out, which is not part of this release; "
                         "use --workers 0 (in-process)")
    if cfg.eval.planner not in PLANNERS:
        raise ValueError(f"unknown planner {cfg.eval.planner!r}; available: {', '.join(PLANNERS)}")
    out = Path(out)
    t0 = time.perf_counter()
    maps, bad = load_maps(cfg)
    for b in bad:
        print(f"skipped map {b['file']}: {b['reason']}")
    if not maps:
        raise MapError(cfg.eval.maps, "none of the maps could be used (reasons above)")
    atomic_write_table(maps_table(maps), out / "maps" / "maps.parquet", "maps")
    per_n, all_rows, skipped_all, table_rows = {}, [], {}, []
    for n in cfg.eval.robots:
        rows, skipped = evaluate_team_size(cfg, maps, n, out)
        summary = summarize(rows)
        per_n[str(n)] = summary | {"skipped": len(skipped)}
        skipped_all[str(n)] = skipped
        all_rows += rows
        table_rows.append((f"{cfg.eval.planner}@{n}", summary))
    metrics = summarize(all_rows) | {
        "planner": cfg.eval.planner, "by_team_size": per_n, "skipped_episodes": skipped_all,
        "bad_maps": bad, "maps": len(maps), "seconds": round(time.perf_counter() - t0, 2),
        "config": to_dict(cfg),
    }
    atomic_write_json(metrics, out / "metrics.json")
    print(format_table(table_rows))
    return metrics
