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


@dataclass
class Shared:
    """A large value every worker reads, published once per version (GRPO's weights): on Ray one object-store
    copy (`ref`, fetched by each actor when its version changes), in-process the value itself."""
    version: int
    value: Any = None
    ref: list | None = None  # [ObjectRef], boxed so that Ray does not resolve it when the unit is sent

    def get(self) -> Any:
        if self.ref is not None:
            import ray

            return ray.get(self.ref[0])
        return self.value


class InProcessRunner:
    """Runs units one after another in this process: no Ray, breakpoints work (`--workers 0`). Its cache lives
    across calls with the same function and ctx, as a Ray actor's does."""

    workers = 0

    def __init__(self):
        self.cache: dict = {}
        self._started: tuple = ()  # (function, ctx) held, so the ctx's identity cannot be reused

    def publish(self, value: Any, version: int) -> Shared:
        return Shared(version, value=value)

    def imap_unordered(self, fn_ref: str, ctx: dict, units: Iterable[Unit]) -> Iterator[UnitResult]:
        fn = resolve_function(fn_ref)
        # as on Ray: the cache lives while the function and the ctx stay the same
        if not self._started or self._started[0] != fn_ref or self._started[1] is not ctx:
            self.cache, self._started = {}, (fn_ref, ctx)
        for unit in units:
            yield call_unit(fn, ctx, unit, self.cache)

    def describe(self) -> str:
        return "in-process (no Ray, one core)"

    def shutdown(self) -> None:
        pass
