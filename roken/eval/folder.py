"""An evaluation folder's files and when they are reused: the config check that refuses a folder made with other
settings, the fingerprint an episodes file is written with (and those of earlier field sets, so old folders
resume), where a team size's and a finished unit's episodes live, and reading them back for a resume."""
from __future__ import annotations

import hashlib
import json
import sys

from ..configtools import LATER_FIELDS, to_dict, with_later_fields, without_later_fields
from ..data import fs
from ..data.store import StoreError, file_metadata, read_episodes, read_json
from ..plan.controller import rollout_config

# plan fields that do not change a Roken episode (where and how fast it runs)
PLAN_RUNTIME_KEYS = ("device", "batch_size", "record_plans")


def refuse_other_config(out: str, cfg, model_id: str = "") -> None:
    """An evaluation folder made with another config, or (for Roken rows) another checkpoint or plan section,
    is not overwritten silently (as generate.py refuses); other team sizes may be added to it."""
    from ..data.build import changed_keys

    path = fs.join(out, "metrics.json")
    if not fs.exists(path):
        return
    try:
        metrics = read_json(path)
        old = metrics.get("config", {})
    except (OSError, ValueError):
        return
    # a field the stored config lacks (added since) reads as the value from before it existed
    old = with_later_fields(old)
    new = with_later_fields(json.loads(json.dumps(to_dict(cfg), default=str)))
    keys = ("map", "task", "expert", "eval")
    changed = [c for c in changed_keys({k: old.get(k) for k in keys}, {k: new[k] for k in keys})
               if not c.startswith(("eval.robots", "eval.planner"))]
    old_model = (metrics.get("model") or {}).get("sha256")
    if model_id and old_model:  # both evaluations ran Roken: the same weights and plan settings, or refuse
        if old_model != model_id:
            changed.append(f"checkpoint: sha256 {old_model} -> {model_id}")
        plan_old = {k: v for k, v in (old.get("plan") or {}).items() if k not in PLAN_RUNTIME_KEYS + ("checkpoint",)}
        plan_new = {k: v for k, v in new["plan"].items() if k not in PLAN_RUNTIME_KEYS + ("checkpoint",)}
        changed += changed_keys(plan_old, plan_new, "plan.")
    if changed:
        raise StoreError(f"{out} holds an evaluation made with a different config ({'; '.join(changed[:6])}); "
                         f"nothing was written. Use a new --out, or --overwrite to replace it")


def fingerprint(cfg, n: int, planner: str = "laplacian", model_id: str = "") -> str:
    """What an episode file depends on: tasks (map, task, eval), the planner's own settings (the expert's, or
    Roken's plan section and weights); fields added since the first folders (configtools.LATER_FIELDS) enter it
    only when they are not at the value from before they existed, so adding a field changes no fingerprint."""
    return fingerprints(cfg, n, planner, model_id)[0]


def fingerprints(cfg, n: int, planner: str = "laplacian", model_id: str = "") -> list[str]:
    """The fingerprint an episode file is written with, then those under which code of each earlier field set
    wrote the same episodes (LATER_FIELDS[k:] left out when at their old value; the last: every field hashed):
    a file written by any of them is resumed."""
    d = _fingerprint_dict(cfg, planner, model_id)
    out = []
    for since in range(len(LATER_FIELDS) + 1):
        fp = hashlib.sha256(json.dumps([without_later_fields(d, since), n], sort_keys=True,
                                       default=str).encode()).hexdigest()[:16]
        if fp not in out:
            out.append(fp)
    return out


def _fingerprint_dict(cfg, planner: str, model_id: str) -> dict:
    d = to_dict(cfg)
    d["eval"] = {k: v for k, v in d["eval"].items() if k not in ("robots", "planner")}
    keys = ("map", "task", "expert", "eval")
    if planner in ("sgg", "gnn"):
        keys = keys + ("sgg",) + (("gnn",) if planner == "gnn" else ())
        if planner == "gnn":
            d["gnn"] = {k: v for k, v in d["gnn"].items() if k != "checkpoint"} | {"weights": model_id}
    elif planner != "laplacian":
        d["plan"] = rollout_config(cfg.plan, planner).__dict__ | {"checkpoint": model_id}
        keys = keys + ("plan",)
    return {k: v for k, v in d.items() if k in keys}


def episode_file(out: str, planner: str, n: int) -> str:
    name = f"n{n:02d}.parquet" if planner == "laplacian" else f"{planner.replace('+', '-')}-n{n:02d}.parquet"
    return fs.join(out, "episodes", name)


def unit_file(out: str, unit_key: str) -> str:
    """Where a finished unit's episodes wait until their team size's file is written (episodes/_units/, which
    readers of episodes/*.parquet never list): a killed evaluation resumes from its finished units."""
    return fs.join(out, "episodes", "_units", f"{unit_key.replace('+', '-')}.parquet")


def _stored(path: str, fps: list[str], **same) -> tuple[list[dict], dict] | None:
    """(rows, metadata) of an episodes file written with any of the fingerprints `fps` and the metadata values
    `same`, else None (missing, unreadable or from another config: the caller runs it again)."""
    if not fs.exists(path):
        return None
    try:
        meta = file_metadata(path)
        if meta.get("fingerprint") in fps and all(meta.get(k) == v for k, v in same.items()):
            return read_episodes(path), meta
    except (StoreError, OSError, ValueError):
        pass
    return None


def reuse(path: str, fps: list[str], n: int) -> tuple[list[dict], list] | None:
    """(rows, skipped) of a team size finished earlier with the same config (any of `fps`), else None."""
    got = _stored(path, fps)
    if got is None:
        return None
    print(f"[N={n}] reusing {path} (same config)", file=sys.stderr)
    return got[0], got[1].get("skipped", [])


def reuse_unit(path: str, fps: list[str], episodes: list[int]) -> list[dict] | None:
    """The rows of a unit finished earlier with the same config (any of `fps`) and episodes, else None."""
    got = _stored(path, fps, episodes=episodes)
    return None if got is None else got[0]
