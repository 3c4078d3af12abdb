"""Expert dataset generation: maps -> tasks -> Laplacian expert -> scored episodes -> Parquet shards.

The job is cut into units of `maps_per_unit` consecutive maps. Unit u is fully determined by the config and
u, and is written as the pair of shards

    maps/unit-{u:05d}.parquet   the unit's maps as planned on (store contract)
    episodes/unit-{u:05d}.parquet   its episodes; metadata: config fingerprint + the unit's summary

each atomically, maps first: an episodes shard under its final name means the unit is finished, so a
re-run skips it, and a killed run leaves nothing half-written. Episode k of the map with global index i
draws its team size from `team_sizes` and its task from the stream seeded by (seed, i, k); its id is
"{map_id}-e{k:02d}". The same command therefore always yields the same ids and the same trajectories,
whichever worker runs which unit and however often the run was interrupted.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..configtools import from_dict
from ..expert import dart
from ..expert.laplacian import ExpertConfig, LaplacianExpert
from ..world.grid import GridMap
from ..world.loaders import MapError, find_map_files, load_map_file
from ..world.maps import SPLITS, MapConfig, generate_map, split_size
from ..world.tasks import Task, TaskConfig, TaskError, check_start, sample_task
from . import fs
from .store import StoreError, atomic_write_table, episode_record, episodes_table, file_metadata, maps_table


def _paper_team_mix() -> dict[int, float]:
    # The paper's mixed dataset is "heavily imbalanced towards the four-robot case" with 2..8 robots
    # (Fig. "Dataset distribution"): 60 % four robots, the rest spread evenly over 2, 3, 5, 6, 7, 8.
    return {2: 1.0, 3: 1.0, 4: 9.0, 5: 1.0, 6: 1.0, 7: 1.0, 8: 1.0}


@dataclass
class DatasetConfig:
    maps: str = "train"  # "train", "val", "eval", or a folder / glob / file of external maps
    num_maps: int | None = None  # at most this many maps (default: the whole split or every file)
    episodes_per_map: int = 10
    team_sizes: dict[int, float] = field(default_factory=_paper_team_mix)  # N -> relative weight
    maps_per_unit: int = 20  # maps per work unit and shard: 200 episodes, so each team size gets a real batch
    seed: int = 0
    keep_failed: bool = False  # keep episodes the expert failed (flagged success=false) in the shards
    # Markov labels (README "Markov labels"): the expert's recorded chunk at step t depends on its hidden state
    # (inertia, spanning-tree hysteresis, reference progress), not only on the positions a model sees; restarted
    # from the same positions it moves 0.49 m differently over the executed moves. With restart_every = k > 0 the
    # expert is also restarted from every k-th step of each kept episode (before its leader reaches the goal),
    # each continuation is kept as an episode, and training chunks start only at an episode's first step
    # (sample_until = 1): every label is then the expert's answer to the positions alone. 0 = off (the paper).
    restart_every: int = 0
    # With expert.disturb > 0 (DART), training chunks of each episode start in the `disturb_window` steps after its
    # disturbance ends (sample_from / sample_until): states off the expert's course, labelled with its recovery.
    # The steps before are kept as the episode's history (a last-move model reads the push). 0 = anywhere.
    disturb_window: int = 16


def check(dc: DatasetConfig, ec: ExpertConfig | None = None) -> None:
    if ec is not None:
        dart.check(ec.disturb, ec.disturb_steps, ec.disturb_mode)  # named before anything is written
        if ec.disturb > 0 and dc.restart_every > 0:
            raise ValueError("expert.disturb and dataset.restart_every choose where chunks start in two ways; "
                             "set one of them (DART episodes: expert.disturb; Markov labels: restart_every)")
    if dc.num_maps is not None and dc.num_maps < 1:
        raise ValueError(f"--num-maps {dc.num_maps}: must be >= 1; omit it to use every map of the split")
    if dc.seed < 0:
        raise ValueError(f"--seed {dc.seed}: must be >= 0")
    if dc.restart_every < 0:
        raise ValueError(f"dataset.restart_every={dc.restart_every}: must be >= 0 (0 = off, k = restart the expert "
                         f"from every k-th step, e.g. 40)")
    if dc.disturb_window < 0:
        raise ValueError(f"dataset.disturb_window={dc.disturb_window}: must be >= 0 (steps after an expert.disturb "
                         f"push where chunks start; 0 = anywhere)")
    if dc.episodes_per_map < 1 or dc.maps_per_unit < 1:
        raise ValueError("dataset.episodes_per_map and dataset.maps_per_unit must be >= 1")
    if not dc.team_sizes or any(n < 1 or w < 0 for n, w in dc.team_sizes.items()) \
            or sum(dc.team_sizes.values()) <= 0:
        raise ValueError(f"dataset.team_sizes must map team sizes >= 1 to weights >= 0 with a positive sum, "
                         f"got {dc.team_sizes}; e.g. --set 'dataset.team_sizes={{4: 1}}'")


def map_sources(dc: DatasetConfig, map_cfg) -> list[tuple[int, str, str | None]]:
    """(global index, map id, file or None) of every map of the dataset, in order."""
    if dc.maps in SPLITS:
        n = split_size(map_cfg, dc.maps)
        n = min(n, dc.num_maps) if dc.num_maps else n
        return [(i, f"{dc.maps}-{i:06d}", None) for i in range(n)]
    files = find_map_files(dc.maps)[:dc.num_maps or None]
    out, seen = [], {}
    for i, f in enumerate(files):
        stem = f.stem
        k = seen.get(stem, 0)
        seen[stem] = k + 1
        out.append((i, f"{stem}-{k}" if k else stem, str(Path(f).resolve())))
    return out


def plan_units(dc: DatasetConfig, map_cfg) -> list[dict]:
    """Unit payloads: {"key": "unit-00003", "maps": [(index, map_id, file), ...]}."""
    sources = map_sources(dc, map_cfg)
    m = dc.maps_per_unit
    return [{"key": f"unit-{u:05d}", "maps": sources[s:s + m]} for u, s in enumerate(range(0, len(sources), m))]


def shard_paths(out: str, key: str) -> tuple[str, str]:
    return fs.join(out, "maps", f"{key}.parquet"), fs.join(out, "episodes", f"{key}.parquet")


def finished_summary(out: str, key: str, fingerprint: str) -> dict | None:
    """The stored summary of a unit finished earlier with the same config, else None."""
    _, ep_path = shard_paths(out, key)
    if not fs.exists(ep_path):
        return None
    try:
        meta = file_metadata(ep_path)
    except (OSError, ValueError):
        return None  # unreadable: regenerate it (the atomic rename replaces it)
    if meta.get("fingerprint") != fingerprint:
        raise StoreError(f"{ep_path} was made with a different config (fingerprint {meta.get('fingerprint')} "
                         f"!= {fingerprint}); write to a new --out folder or delete the old one")
    return meta.get("unit")


def _load(entry, split: str, cfg) -> GridMap:
    index, map_id, file = entry
    if file is None:
        return generate_map(cfg.map, split, index)
    gm = load_map_file(file, cfg.map)
    gm.map_id = map_id
    return gm


def _team_size(rng: np.random.Generator, mix: dict[int, float]) -> int:
    sizes = sorted(mix)
    w = np.array([mix[n] for n in sizes], dtype=float)
    return int(sizes[rng.choice(len(sizes), p=w / w.sum())])


@dataclass
class GenerationSections:
    """The config sections a generation unit reads (a stage takes its own sections, not the root config)."""
    map: MapConfig = field(default_factory=MapConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)


def generate_unit(ctx: dict, payload: dict, cache: dict) -> dict:
    """Worker function (roken.units): run one unit, write its two shards, return its small summary."""
    if "cfg" not in cache:
        sections = ("map", "task", "expert", "dataset")
        cache["cfg"] = from_dict(GenerationSections, {k: ctx["config"][k] for k in sections})
    cfg = cache["cfg"]
    dc = cfg.dataset
    key, out = payload["key"], ctx["out"]
    maps, bad, tasks, skipped = [], [], {}, []
    for entry in payload["maps"]:
        try:
            gm = _load(entry, dc.maps, cfg)
        except MapError as e:
            bad.append({"file": e.path, "reason": e.reason})
            continue
        maps.append(gm)
        index = entry[0]
        for k in range(dc.episodes_per_map):
            rng = np.random.default_rng([dc.seed, index, k])
            n = _team_size(rng, dc.team_sizes)
            try:
                task = sample_task(gm, n, cfg.task, rng, seed=index * dc.episodes_per_map + k)
            except TaskError as err:
                skipped.append({"episode_id": f"{gm.map_id}-e{k:02d}", "reason": str(err)})
                continue
            tasks.setdefault(n, []).append((f"{gm.map_id}-e{k:02d}", task))
    by_id = {m.map_id: m for m in maps}
    expert = LaplacianExpert(cfg.expert, cfg.task)
    rows, by_n, steps = [], {}, 0
    for n in sorted(tasks):  # one expert call per team size: a batch holds one team size
        group = tasks[n]
        for i, ep in expert.run([t for _, t in group], by_id):
            episode_id, task = group[i]
            row = episode_record(episode_id, "laplacian", task, by_id[task.map_id], ep.positions, cfg.task,
                                 task.seed) | disturbance_window(ep.info.get("disturbed_at", -1), cfg.expert, dc)
            stats = by_n.setdefault(str(n), [0, 0, 0])  # attempted, succeeded, kept
            stats[0] += 1
            stats[1] += int(row["success"])
            steps += row["num_steps"]
            if row["success"] or dc.keep_failed:
                stats[2] += 1
                rows.append(row)
    extra = {}
    if dc.restart_every > 0:  # Markov labels: chunks only at an episode's first step, the restarts' included
        restarts = restart_rows(rows, by_id, expert, cfg.task, dc.restart_every)
        rows = [r | {"sample_until": 1} for r in rows] + [r for r in restarts if r["success"] or dc.keep_failed]
        extra["restarts"] = {"states": len(restarts), "succeeded": sum(bool(r["success"]) for r in restarts)}
    rows.sort(key=lambda r: r["episode_id"])
    summary = {"unit": key, "maps": len(maps), "episodes": len(rows), "by_team_size": by_n, "steps": steps,
               "bad_maps": bad, "skipped": skipped} | extra
    maps_path, ep_path = shard_paths(out, key)
    atomic_write_table(maps_table(maps), maps_path, "maps", {"fingerprint": ctx["fingerprint"]})
    atomic_write_table(episodes_table(rows), ep_path, "episodes",
                       {"fingerprint": ctx["fingerprint"], "unit": summary})
    return summary


def disturbance_window(at: int, ec: ExpertConfig, dc: DatasetConfig) -> dict:
    """The columns that make a DART episode's training chunks start right after its disturbance ({} if none)."""
    if at < 0 or dc.disturb_window <= 0:
        return {}
    start = at + ec.disturb_steps
    return {"source": "dart", "sample_from": start, "sample_until": start + dc.disturb_window}


def restart_rows(rows: list[dict], maps: dict[str, GridMap], expert: LaplacianExpert, tc: TaskConfig,
                 every: int) -> list[dict]:
    """The expert restarted from every `every`-th step of each episode in `rows`, before its leader first comes
    within eps_goal of the goal; each continuation (to the goal or the step limit) as an episode row with id
    "{episode_id}-r{t:04d}" and sample_until = 1. A state the expert cannot start from is skipped (check_start)."""
    groups: dict[int, list[tuple[str, Task]]] = {}
    for r in rows:
        P = np.asarray(r["positions"], np.float64)
        goal, leader = np.asarray(r["goal"], np.float64), int(r["leader"])
        near = np.flatnonzero(np.linalg.norm(P[:, leader] - goal, axis=-1) <= tc.eps_goal)
        end = int(near[0]) if len(near) else len(P) - 1
        for t in range(every, end, every):
            if check_start(maps[r["map_id"]], P[t], tc) is None:
                task = Task(r["map_id"], P[t].copy(), goal.copy(), leader, seed=int(r["seed"]))
                groups.setdefault(P.shape[1], []).append((f"{r['episode_id']}-r{t:04d}", task))
    out = []
    for n in sorted(groups):  # one expert call per team size
        group = groups[n]
        for i, ep in expert.run([t for _, t in group], maps):
            episode_id, task = group[i]
            out.append(episode_record(episode_id, "laplacian", task, maps[task.map_id], ep.positions, tc, task.seed)
                       | {"sample_until": 1})
    return out
