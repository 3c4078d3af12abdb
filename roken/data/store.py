"""Episode store: the Parquet contract of ARCHITECTURE.md, atomic writes, a validating reader.

A dataset or evaluation folder holds maps/*.parquet and episodes/*.parquet. Plain Arrow types only (no
extension types), so pyarrow, pandas, Ray Data and DuckDB read it as is; `schema_version` and `kind` sit in
the file metadata. Files are written under a temporary name in the same folder and renamed into place, so
a reader never sees half a file and a crash leaves no partial shard under the final name.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..world.grid import GridMap
from ..world.metrics import episode_metrics
from ..world.tasks import Task, TaskConfig
from . import fs

SCHEMA_VERSION = "1"

MAPS_SCHEMA = pa.schema([
    ("map_id", pa.string()),
    ("height", pa.int32()),
    ("width", pa.int32()),
    ("occupancy", pa.binary()),
    ("source", pa.string()),
])

EPISODES_SCHEMA = pa.schema([
    ("episode_id", pa.string()),
    ("map_id", pa.string()),
    ("planner", pa.string()),
    ("num_robots", pa.int32()),
    ("leader", pa.int32()),
    ("num_steps", pa.int32()),
    ("goal", pa.list_(pa.float32(), 2)),
    ("positions", pa.list_(pa.float32())),
    ("success", pa.bool_()),
    ("reach", pa.bool_()),
    ("obstacle_collision", pa.bool_()),
    ("inter_collision", pa.bool_()),
    ("connectivity", pa.bool_()),
    ("path_length", pa.float32()),
    ("astar_length", pa.float32()),
    ("seed", pa.int64()),
])


# Columns a planner may add (Roken): safety stops, and the chunk planned at each re-plan (for plots and GIFs):
# plans holds len(plan_steps) * N * H * 2 values, layout [re-plan][robot][chunk move][x, y].
# DAgger's relabelled episodes say where they come from: source "dagger" (an expert dataset's rows are "expert",
# the column absent; "self": a successful rollout of the learner kept as executed, dagger.keep_success; "dart": an
# expert episode pushed off course once, expert.disturb, whose chunks start after the push) and the
# round that visited the start state; training chunks of such an episode start before step `sample_until`
# (0 = anywhere), near the learner's state it was relabelled from, and at or after step `sample_from`: the steps
# before it are the learner's own last moves before that state (dagger.history_steps; 0 = none), kept as history.
OPTIONAL_EPISODE_COLUMNS = {"holds": pa.int32(), "plan_steps": pa.list_(pa.int32()), "plans": pa.list_(pa.float32()),
                            "source": pa.string(), "round": pa.int32(), "sample_until": pa.int32(),
                            "sample_from": pa.int32()}


class StoreError(ValueError):
    """A file that does not follow the episode-store contract, with the file and the reason."""


def table_bytes(table: pa.Table, kind: str, extra_meta: dict | None = None) -> bytes:
    """`table` as Parquet bytes, with `schema_version`, `kind` and `extra_meta` (JSON) in its metadata."""
    meta = {b"schema_version": SCHEMA_VERSION.encode(), b"kind": kind.encode()}
    for k, v in (extra_meta or {}).items():
        meta[k.encode()] = json.dumps(v, default=_json_default).encode()
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def atomic_write_table(table: pa.Table, path: str | Path, kind: str, extra_meta: dict | None = None) -> str:
    """Write `table` to `path` (local path or URI) atomically; see `roken.data.fs.write_atomic`."""
    return fs.write_atomic(path, table_bytes(table, kind, extra_meta))


def strict_json(obj):
    """obj with every NaN / infinity replaced by None: strict JSON parsers reject NaN, so it is written null."""
    if isinstance(obj, dict):
        return {k: strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    return obj


def atomic_write_json(obj: dict, path: str | Path) -> str:
    text = json.dumps(strict_json(obj), indent=2, default=_json_default, allow_nan=False)
    return fs.write_atomic(path, (text + "\n").encode())


def read_json(path: str | Path) -> dict:
    return json.loads(fs.read_bytes(path))


def file_metadata(path: str | Path) -> dict:
    """The JSON metadata entries of a store file (schema_version and kind as plain strings)."""
    filesystem, p = fs.resolve(path)
    meta = pq.read_schema(p, filesystem=filesystem).metadata or {}
    out = {}
    for k, v in meta.items():
        key = k.decode()
        if key in ("schema_version", "kind"):
            out[key] = v.decode()
        elif not key.startswith("ARROW"):
            try:
                out[key] = json.loads(v)
            except ValueError:
                out[key] = v.decode(errors="replace")
    return out


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def maps_table(maps: list[GridMap]) -> pa.Table:
    return pa.Table.from_pylist([{
        "map_id": m.map_id, "height": m.shape[0], "width": m.shape[1],
        "occupancy": np.ascontiguousarray(m.occupancy, dtype=np.uint8).tobytes(), "source": m.source,
    } for m in maps], schema=MAPS_SCHEMA)


def episodes_table(rows: list[dict]) -> pa.Table:
    """rows: dicts with the EPISODES_SCHEMA columns; `positions` may be a (T+1, N, 2) array."""
    out = []
    for r in rows:
        r = dict(r)
        pos = np.asarray(r["positions"], dtype=np.float32)
        if pos.ndim == 3:
            r.setdefault("num_steps", pos.shape[0] - 1)
            r.setdefault("num_robots", pos.shape[1])
        r["positions"] = pos.reshape(-1)
        r["goal"] = np.asarray(r["goal"], dtype=np.float32).reshape(2)
        out.append(r)
    extra = [pa.field(k, t) for k, t in OPTIONAL_EPISODE_COLUMNS.items() if out and k in out[0]]
    return pa.Table.from_pylist(out, schema=pa.schema(list(EPISODES_SCHEMA) + extra))


def episode_record(episode_id: str, planner: str, task: Task, gm: GridMap, positions: np.ndarray,
                   task_cfg: TaskConfig, seed: int) -> dict:
    """One episodes-table row: the trajectory scored by the shared metrics."""
    m = episode_metrics(positions, gm, task.goal, task.leader, task_cfg)
    return {
        "episode_id": episode_id, "map_id": task.map_id, "planner": planner,
        "num_robots": positions.shape[1], "leader": task.leader, "num_steps": len(positions) - 1,
        "goal": task.goal, "positions": positions, "success": m.success, "reach": m.reach,
        "obstacle_collision": m.obstacle_collision, "inter_collision": m.inter_collision,
        "connectivity": m.connectivity, "path_length": m.path_length, "astar_length": m.astar_length,
        "seed": seed,
    }


def _read(path: str | Path, kind: str, schema: pa.Schema, columns: list[str] | None = None) -> pa.Table:
    """The validated table; with `columns`, only those are read (and checked), e.g. metrics without the plans."""
    if columns is not None:
        schema = pa.schema([f for f in schema if f.name in columns])
    try:
        filesystem, p = fs.resolve(path)
        table = pq.read_table(p, filesystem=filesystem, columns=columns)
    except (pa.ArrowInvalid, OSError) as e:
        raise StoreError(f"{path}: not a readable Parquet file ({e}); delete it and re-run to regenerate it") from None
    meta = table.schema.metadata or {}
    version = meta.get(b"schema_version", b"").decode()
    if version != SCHEMA_VERSION:
        raise StoreError(f"{path}: schema_version {version or 'missing'!r}, this code reads {SCHEMA_VERSION!r}")
    got = meta.get(b"kind", b"").decode()
    if got != kind:
        raise StoreError(f"{path}: holds a {got or 'unknown'!r} table, expected {kind!r}")
    missing = [f.name for f in schema if f.name not in table.column_names]
    if missing:
        raise StoreError(f"{path}: missing columns {missing}")
    for f in schema:
        if not table.schema.field(f.name).type.equals(f.type):
            raise StoreError(f"{path}: column {f.name} has type {table.schema.field(f.name).type}, expected {f.type}")
    return table


def read_maps(path: str | Path) -> dict[str, GridMap]:
    table = _read(path, "maps", MAPS_SCHEMA)
    out = {}
    for r in table.to_pylist():
        occ = np.frombuffer(r["occupancy"], dtype=np.uint8)
        if occ.size != r["height"] * r["width"]:
            raise StoreError(f"{path}: map {r['map_id']} has {occ.size} occupancy bytes, "
                             f"expected {r['height']} x {r['width']}")
        if not np.isin(occ, [0, 1]).all():
            raise StoreError(f"{path}: map {r['map_id']} occupancy is not binary")
        out[r["map_id"]] = GridMap(r["map_id"], occ.reshape(r["height"], r["width"]).copy(), r["source"] or "")
    return out


def read_episodes(path: str | Path) -> list[dict]:
    """Episode rows with `positions` as (T+1, N, 2) float32 arrays; validated row by row."""
    table = _read(path, "episodes", EPISODES_SCHEMA)
    rows = table.to_pylist()
    for r in rows:
        N, T = r["num_robots"], r["num_steps"]
        pos = np.asarray(r["positions"], dtype=np.float32)
        if N < 1 or T < 0 or pos.size != (T + 1) * N * 2:
            raise StoreError(f"{path}: episode {r['episode_id']} has {pos.size} position values, "
                             f"expected (num_steps+1) * num_robots * 2 = {(T + 1) * N * 2}")
        if not 0 <= r["leader"] < N:
            raise StoreError(f"{path}: episode {r['episode_id']} leader {r['leader']} not in 0..{N - 1}")
        r["positions"] = pos.reshape(T + 1, N, 2)
        r["goal"] = np.asarray(r["goal"], dtype=np.float32)
    return rows


def read_episode_columns(path: str | Path, columns: list[str]) -> pa.Table:
    """Some EPISODES_SCHEMA columns of an episodes file, checked like read_episodes (cheap: no trajectories
    unless asked for)."""
    return _read(path, "episodes", EPISODES_SCHEMA, columns)


def read_run(folder: str | Path) -> tuple[dict[str, GridMap], list[dict]]:
    """All maps and episodes of a dataset / evaluation folder (path or URI); every episode's map must be
    present and every episode id unique."""
    map_files = fs.list_files(fs.join(folder, "maps"), ".parquet")
    ep_files = fs.list_files(fs.join(folder, "episodes"), ".parquet")
    if not map_files or not ep_files:
        raise StoreError(f"{folder}: expected maps/*.parquet and episodes/*.parquet")
    maps: dict[str, GridMap] = {}
    for f in map_files:
        maps.update(read_maps(f))
    episodes = [e for f in ep_files for e in read_episodes(f)]
    orphans = sorted({e["map_id"] for e in episodes} - set(maps))
    if orphans:
        raise StoreError(f"{folder}: episodes refer to maps missing from maps/: {orphans[:5]}")
    ids = [e["episode_id"] for e in episodes]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})[:5]
        raise StoreError(f"{folder}: duplicated episode ids {dup}")
    return maps, episodes


def check_manifest(folder: str | Path, episodes: list[dict]) -> str:
    """Compare a dataset's manifest.json with its files: every listed shard present with its row count and no
    shard missing from the list. Returns a one-line description; raises StoreError on a mismatch."""
    path = fs.join(folder, "manifest.json")
    if not fs.exists(path):
        if fs.exists(fs.join(folder, "metrics.json")):
            return "evaluation folder (metrics.json; evaluations have no manifest)"
        return "no manifest.json: not a dataset written by pipelines/generate.py (a dataset has one)"
    m = read_json(path)
    if "shards" not in m:
        return f"manifest status {m.get('status')!r} (run not finished: re-run its command)"
    listed = {fs.join(folder, s["episodes"]): s["rows"] for s in m["shards"]}
    present = set(fs.list_files(fs.join(folder, "episodes"), ".parquet"))
    if set(listed) != present:
        raise StoreError(f"{folder}: manifest lists {len(listed)} episode shards, the folder has {len(present)} "
                         f"(e.g. {sorted(set(listed) ^ present)[:3]}); re-run the generating command")
    filesystem, _ = fs.resolve(folder)
    bad = [f for f in present if pq.read_metadata(fs.resolve(f)[1], filesystem=filesystem).num_rows != listed[f]]
    if bad or m.get("episodes") != len(episodes):
        raise StoreError(f"{folder}: row counts differ from manifest.json ({bad[:3] or 'total'})")
    return f"manifest {m.get('status')}, {len(listed)} shards"
