"""The dataset driver: plan units, skip finished ones, run the rest on a runner, write manifest.json.

Ray-free: `pipelines/generate.py` passes a `roken.ray_pool.RayRunner`, `--workers 0` an `InProcessRunner`,
and both produce byte-identical shards (a unit's output depends only on the config and the unit).
"""
from __future__ import annotations

import hashlib
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

from ..configtools import to_dict, without_later_fields
from ..progress import Progress
from ..units import Unit
from . import fs
from .generation import check, finished_summary, plan_units, shard_paths
from .store import SCHEMA_VERSION, StoreError, atomic_write_json, read_json

WORKER_FN = "roken.data.generation:generate_unit"


def fingerprint(cfg) -> str:
    """Hash of everything that shapes the episodes (not of how many workers made them)."""
    d = {k: v for k, v in to_dict(cfg).items() if k in ("map", "task", "expert", "dataset")}
    d = without_later_fields(d)  # fields added since at their old value: datasets made before keep their fingerprint
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def code_version() -> dict:
    from importlib import metadata

    root = Path(__file__).resolve().parents[2]
    try:
        version = metadata.version("roken")
    except metadata.PackageNotFoundError:
        version = None
    try:
        sha = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        sha = None
    return {"roken": version, "git": sha, "python": platform.python_version(), "path": str(root)}


def _check_existing(out: str, fp: str, cfg_dict: dict) -> None:
    path = fs.join(out, "manifest.json")
    if not fs.exists(path):
        return
    try:
        old = read_json(path)
    except (OSError, ValueError):
        return
    if old.get("fingerprint") not in (None, fp):
        changed = changed_keys(old.get("config", {}), cfg_dict)
        raise StoreError(f"{out} holds a dataset made with a different config ({'; '.join(changed[:6]) or 'code'}); "
                         f"its shards are kept. Write to a new --out folder, or re-run with the old config to "
                         f"finish it")


def changed_keys(old: dict, new: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(old) | set(new), key=str):
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += changed_keys(a, b, f"{prefix}{k}.")
        elif json.dumps(a, sort_keys=True, default=str) != json.dumps(b, sort_keys=True, default=str):
            out.append(f"{prefix}{k}: {a} -> {b}")
    return out


def summary_table(by_n: dict, total_s: float, episodes: int, runner_desc: str, units: dict,
                  retries: int) -> str:
    lines = [f"{'N':>4}{'attempted':>11}{'expert success':>16}{'kept':>8}", "-" * 39]
    tot = [0, 0, 0]
    for n in sorted(by_n, key=int):
        a, s, k = by_n[n]
        tot = [tot[0] + a, tot[1] + s, tot[2] + k]
        lines.append(f"{n:>4}{a:>11d}{s / max(a, 1):>16.3f}{k:>8d}")
    lines.append(f"{'all':>4}{tot[0]:>11d}{tot[1] / max(tot[0], 1):>16.3f}{tot[2]:>8d}")
    rate = units["episodes_run"] / total_s if total_s > 0 else 0.0
    lines.append(f"units: {units['run']} run, {units['reused']} reused, {units['failed']} failed, "
                 f"{retries} retried; {episodes} episodes in the dataset")
    lines.append(f"throughput: {units['episodes_run']} expert episodes in {total_s:.1f} s = {rate:.1f} "
                 f"episodes/s ({runner_desc})")
    return "\n".join(lines)


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """'K/N' -> (K, N) with 0 <= K < N."""
    if text is None:
        return None
    try:
        k, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard {text!r}: expected K/N, e.g. 0/4 for the first of 4 processes") from None
    if n < 1 or not 0 <= k < n:
        raise ValueError(f"--shard {text}: needs N >= 1 and 0 <= K < N")
    return k, n


def build_dataset(cfg, out: str, runner, shard: tuple[int, int] | None = None) -> dict:
    """Generate (or finish) the dataset described by `cfg` in folder or URI `out`; returns the manifest.

    shard=(K, N) runs only the units u with u % N == K (N processes without Ray make one dataset together: a
    Slurm array, a GPU box); the manifest lists every unit finished so far, so the last process to finish
    (or a plain run afterwards, which reuses every shard) writes it complete."""
    check(cfg.dataset)
    out = str(out)
    fp = fingerprint(cfg)
    _check_existing(out, fp, json.loads(json.dumps(to_dict(cfg), default=str)))
    for sub in ("maps", "episodes"):
        fs.remove_stale_temporaries(fs.join(out, sub))
    t0 = time.perf_counter()
    plans = plan_units(cfg.dataset, cfg.map)
    summaries: dict[str, dict] = {}
    todo = []
    for u, p in enumerate(plans):
        s = finished_summary(out, p["key"], fp)
        if s is not None:
            summaries[p["key"]] = s
        elif shard is None or u % shard[1] == shard[0]:
            todo.append(Unit(p["key"], p, size=len(p["maps"]) * cfg.dataset.episodes_per_map))
    manifest = {
        "kind": "roken-dataset", "schema_version": SCHEMA_VERSION, "status": "running", "fingerprint": fp,
        "units_total": len(plans), "config": to_dict(cfg), "code_version": code_version(),
        "command": sys.argv,
    }
    atomic_write_json(manifest, fs.join(out, "manifest.json"))
    if shard is not None:
        print(f"[generate] shard {shard[0]}/{shard[1]}: units u with u % {shard[1]} == {shard[0]}", file=sys.stderr)
    if 0 < len(todo) < runner.workers:
        print(f"[generate] note: {len(todo)} unit{'s' * (len(todo) != 1)} for {runner.workers} workers: only "
              f"{len(todo)} will work (a unit is dataset.maps_per_unit={cfg.dataset.maps_per_unit} maps; lower it "
              f"to spread a small run)", file=sys.stderr)
    print(f"[generate] {len(plans)} unit{'s' * (len(plans) != 1)} of {cfg.dataset.maps_per_unit} maps x "
          f"{cfg.dataset.episodes_per_map} "
          f"episodes -> {out}: {len(summaries)} finished earlier, {len(todo)} to run on "
          f"{runner.describe() if runner.workers == 0 else f'{runner.workers} Ray workers'}", file=sys.stderr)
    failures, worker_s, episodes_run = [], 0.0, 0
    bar = Progress(sum(u.size for u in todo), "[generate]", unit="ep")
    ctx = {"config": to_dict(cfg), "out": out, "fingerprint": fp}
    interrupted = False
    try:
        for r in runner.imap_unordered(WORKER_FN, ctx, todo):
            if r.ok:
                summaries[r.unit.key] = r.value
                worker_s += r.seconds
                episodes_run += sum(v[0] for v in r.value["by_team_size"].values())
            else:
                failures.append({"unit": r.unit.key, "error": r.error, "attempts": r.attempts})
                print(f"[generate] unit {r.unit.key} failed after {r.attempts} attempt(s): {r.error}",
                      file=sys.stderr)
            bar.update(r.unit.size)
    except KeyboardInterrupt:  # Ctrl-C: record what is finished; finished shards are kept for the resume
        interrupted = True
    finally:
        runner.shutdown()
    total_s = time.perf_counter() - t0
    manifest = _finish(cfg, out, manifest, plans, summaries, failures, runner, total_s, worker_s, episodes_run,
                       len(todo), interrupted)
    if interrupted:
        raise Interrupted(f"interrupted; {len(summaries)} of {len(plans)} units written to {out}; re-run the same "
                          f"command to resume")
    return manifest


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during a build, after the manifest recorded the state (status `interrupted`)."""


def _finish(cfg, out, manifest, plans, summaries, failures, runner, total_s, worker_s, episodes_run, n_run,
            interrupted: bool = False):
    by_n: dict[str, list[int]] = {}
    shards, bad_maps, skipped = [], [], []
    missing = 0
    for p in plans:
        s = summaries.get(p["key"])
        if s is None:
            missing += 1
            continue
        maps_path, ep_path = shard_paths(out, p["key"])
        shards.append({"unit": p["key"], "episodes": f"episodes/{p['key']}.parquet",
                       "maps": f"maps/{p['key']}.parquet", "rows": s["episodes"], "map_rows": s["maps"]})
        for n, v in s["by_team_size"].items():
            acc = by_n.setdefault(n, [0, 0, 0])
            for j in range(3):
                acc[j] += v[j]
        bad_maps += s["bad_maps"]
        skipped += s["skipped"]
    retries = getattr(runner, "retries", 0)
    units = {"run": n_run - len(failures), "reused": len(plans) - n_run, "failed": len(failures),
             "episodes_run": episodes_run}
    episodes = sum(s["rows"] for s in shards)
    manifest |= {
        "status": "interrupted" if interrupted else "complete" if not failures and not missing else "incomplete",
        "units_missing": missing,
        "shards": shards, "episodes": episodes, "maps": sum(s["map_rows"] for s in shards),
        "by_team_size": {n: {"attempted": a, "success": s, "kept": k, "success_rate": s / max(a, 1)}
                         for n, (a, s, k) in sorted(by_n.items(), key=lambda kv: int(kv[0]))},
        "failures": failures, "bad_maps": bad_maps, "skipped_tasks": skipped, "retries": retries,
        "throughput": {"seconds": round(total_s, 2), "episodes_run": episodes_run,
                       "episodes_per_s": round(episodes_run / total_s, 2) if total_s > 0 else None,
                       "worker_seconds": round(worker_s, 2), "workers": runner.workers},
    }
    atomic_write_json(manifest, fs.join(out, "manifest.json"))
    for b in bad_maps:
        print(f"[generate] skipped map {b['file']}: {b['reason']}", file=sys.stderr)
    print(summary_table(by_n, total_s, episodes, runner.describe(), units, retries))
    if missing and not failures:
        print(f"[generate] {missing} unit(s) of other shards not written yet; when every --shard process has "
              f"finished, the dataset is complete (a plain run of the same command checks it)", file=sys.stderr)
    if failures:
        print(f"[generate] {len(failures)} unit(s) failed (listed in manifest.json); re-run the same command "
              f"to retry them - finished units are kept", file=sys.stderr)
    return manifest
