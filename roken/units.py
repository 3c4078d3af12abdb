"""Work units and the in-process runner; `roken.ray_pool.RayRunner` runs the same units on Ray actors.

A pipeline cuts its job into units with deterministic keys (a unit's output depends only on the config and
the unit, never on which worker ran it or when) and names a worker function by "module:function":

    fn(ctx: dict, payload, cache: dict) -> result

`ctx` is the same for every unit (the resolved config, shared inputs), `payload` is the unit's own small
description, `cache` persists across the units one worker runs (maps, fields, expert objects). A runner
yields a `UnitResult` per unit as units finish, in any order; a unit that raised comes back with `error`
set instead of stopping the others, so one bad map never costs a 5000-map run.
"""
from __future__ import annotations

import importlib
import os
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator


@dataclass(frozen=True)
class Unit:
    key: str  # deterministic name: the shard name for generation, "n04-u001" for evaluation
    payload: Any = None
    size: int = 1  # work items (episodes) in the unit, for progress and throughput


@dataclass
class UnitResult:
    unit: Unit
    value: Any = None
    error: str | None = None  # one-line reason when the unit failed
    seconds: float = 0.0  # wall time inside the worker function
    attempts: int = 1
    worker: str = ""  # "pid@host" of the process that ran it

    @property
    def ok(self) -> bool:
        return self.error is None


def resolve_function(ref: str) -> Callable:
    module, _, name = ref.partition(":")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"worker function {ref!r} not found ({e})") from None


def in_ray_job() -> bool:
    """True inside a driver started by `ray job submit` (the job supervisor sets this variable)."""
    return bool(os.environ.get("RAY_JOB_SUBMISSION_ID"))


def worker_name() -> str:
    return f"{os.getpid()}@{os.uname().nodename}"


def call_unit(fn: Callable, ctx: dict, unit: Unit, cache: dict) -> UnitResult:
    """Run one unit, timing it and turning an exception into a failed result with its traceback printed."""
    t0 = time.perf_counter()
    try:
        value = fn(ctx, unit.payload, cache)
    except Exception as e:  # noqa: BLE001  (reported per unit; the run goes on)
        traceback.print_exc()
        return UnitResult(unit, error=f"{type(e).__name__}: {e}", seconds=time.perf_counter() - t0,
                          worker=worker_name())
    return UnitResult(unit, value, seconds=time.perf_counter() - t0, worker=worker_name())


class InProcessRunner:
    """Runs units one after another in this process: no Ray, breakpoints work (`--workers 0`)."""

    workers = 0

    def imap_unordered(self, fn_ref: str, ctx: dict, units: Iterable[Unit]) -> Iterator[UnitResult]:
        fn = resolve_function(fn_ref)
        cache: dict = {}
        for unit in units:
            yield call_unit(fn, ctx, unit, cache)

    def describe(self) -> str:
        return "in-process (no Ray, one core)"

    def shutdown(self) -> None:
        pass
