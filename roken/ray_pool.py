"""The thin Ray layer: connect to a cluster, and run work units on a pool of actors.

This is the only module in `roken` that imports Ray; everything it runs is plain `roken` code (see
`roken.units`). The driver keeps at most `per_worker` units queued on each actor, so memory stays bounded
however many thousand units a job has, and a worker never waits for its next unit. Actors are restarted by
Ray when their process dies; the driver re-queues the units that were lost with it, up to `max_attempts`
times, and reports a unit that keeps killing its worker as failed instead of retrying forever.
"""
from __future__ import annotations

import os
import secrets
import socket
import sys
import time
from collections import deque
from typing import Iterable, Iterator

# Before Ray is imported: it reads the mode once. Token authentication stays on unless the user turned it
# off explicitly (RAY_AUTH_MODE=disabled).
os.environ.setdefault("RAY_AUTH_MODE", "token")

import ray  # noqa: E402
from ray.exceptions import (ActorUnavailableError, AuthenticationError, GetTimeoutError, ObjectLostError,
                            OutOfMemoryError, RayActorError, WorkerCrashedError)

from .units import Shared, Unit, UnitResult, call_unit, in_ray_job, resolve_function, worker_name  # noqa: E402

# Failures of the process, not of the unit's code (that is caught inside call_unit): worth another attempt.
RETRYABLE = (RayActorError, WorkerCrashedError, OutOfMemoryError, ObjectLostError)


def connect(address: str | None = None, local: bool = False, num_cpus: int | None = None,
            code_root: str | None = None, dashboard: bool = False) -> dict:
    """Start or join a Ray cluster with token authentication on; returns the cluster's resources.

    local=True starts a private cluster on this machine with `num_cpus` (default: every core) - the laptop
    mode that replaces the `local_mode=True` Ray removed in 2.55. Otherwise join `address`, $RAY_ADDRESS
    (set for `ray job submit` drivers), or a cluster started on this machine with `ray start`.
    `dashboard` starts the local cluster's dashboard on 127.0.0.1 (Ray Train uses its state API).
    `code_root` is put on the workers' PYTHONPATH so they import this checkout without installing it
    (a submitted job gets the same from its uploaded working directory instead).
    """
    if ray.is_initialized():  # a pipeline that runs several stages (post-training, then its evaluation)
        return ray.cluster_resources()
    if local and not _has_token():
        # A private cluster gets a private secret; it lives in this process's environment only (the
        # cluster processes started by ray.init inherit it), nothing is written to ~/.ray.
        os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    runtime_env = None
    if code_root and not in_ray_job():
        path = os.pathsep.join(p for p in (code_root, os.environ.get("PYTHONPATH", "")) if p)
        runtime_env = {"env_vars": {"PYTHONPATH": path}}
    kwargs = dict(runtime_env=runtime_env, logging_level="WARNING", log_to_driver=True)
    if local:
        # Ray Train needs the dashboard's state API (without it, its placement-group cleaner floods the log);
        # bound to 127.0.0.1 on a port Ray picks.
        extra = dict(include_dashboard=True, dashboard_host="127.0.0.1", dashboard_port=None) if dashboard \
            else dict(include_dashboard=False)
        ray.init(address="local", num_cpus=num_cpus or os.cpu_count(), **extra, **kwargs)
    else:
        target = address or os.environ.get("RAY_ADDRESS") or "auto"
        _check_reachable(target)
        if not _has_token():
            raise ConnectionError(
                f"no Ray authentication token for the cluster at {target!r}: token authentication is on "
                f"(RAY_AUTH_MODE=token); put the cluster's token in ~/.ray/auth_token or RAY_AUTH_TOKEN")
        try:
            ray.init(address=target, **kwargs)
        except AuthenticationError as e:
            raise ConnectionError(f"the Ray cluster at {target!r} refused this machine's token ({e}); use the "
                                  f"token the cluster was started with (RAY_AUTH_TOKEN or ~/.ray/auth_token)") from None
        except ConnectionError as e:
            if target != "auto" and "://" not in target:  # it answered _check_reachable: it is the handshake
                raise ConnectionError(
                    f"something answers at {target} but Ray could not join it ({e}): most often this machine's "
                    f"token is not the cluster's (RAY_AUTH_TOKEN or ~/.ray/auth_token; the GCS log says "
                    f"InvalidAuthToken), or {target} is not the cluster's GCS port") from None
            raise ConnectionError(
                f"no Ray cluster at {target!r} ({e}). Start one with cluster/start-head.sh, pass "
                f"--address HOST:PORT, or use --local for a cluster on this machine") from None
    return ray.cluster_resources()


def _check_reachable(target: str) -> None:
    """A HOST:PORT address where nothing listens is named as such, before Ray's own (token) errors."""
    if target == "auto" or "://" in target or ":" not in target:
        return
    host, _, port = target.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=3).close()
    except (OSError, ValueError):
        raise ConnectionError(f"no Ray cluster answers at {target} (nothing accepts connections there). Start one "
                              f"with cluster/start-head.sh, check --address HOST:PORT (the GCS port, 6379 by "
                              f"default), or use --local for a cluster on this machine") from None


def _has_token() -> bool:
    path = os.environ.get("RAY_AUTH_TOKEN_PATH") or os.path.expanduser("~/.ray/auth_token")
    return bool(os.environ.get("RAY_AUTH_TOKEN")) or os.path.isfile(path)


# Units run one at a time in the default group; `progress` has its own group (a thread), so the driver can ask
# how far a long unit has got while it runs.
@ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=0, concurrency_groups={"progress": 1})
class UnitWorker:
    def __init__(self, fn_ref: str):
        self.fn = resolve_function(fn_ref)
        self.ctx, self.ctx_id = None, None
        self.cache: dict = {}
        self.ticks = 0  # items (episodes) this actor finished inside units, reported by the unit's function

    def name(self) -> str:
        return worker_name()

    @ray.method(concurrency_group="progress")
    def progress(self) -> int:
        return self.ticks

    def _tick(self) -> None:
        self.ticks += 1

    def run(self, ctx_box: list, unit: Unit) -> UnitResult:
        # ctx_box = [ObjectRef]: boxed so Ray does not fetch it for every call; fetched once per actor (and
        # again after a restart), then kept with the worker's cache.
        if self.ctx_id != ctx_box[0].hex():
            self.ctx, self.ctx_id, self.cache = ray.get(ctx_box[0]), ctx_box[0].hex(), {}
        ctx = self.ctx | {"on_episode": self._tick} if self.ctx.get("report_episodes") else self.ctx
        return call_unit(self.fn, ctx, unit, self.cache)


class RayRunner:
    def __init__(self, workers: int, per_worker: int = 2, max_attempts: int = 3, log=None, num_gpus: float = 0):
        if workers < 1:
            raise ValueError(f"RayRunner needs workers >= 1, got {workers}")
        self.workers, self.per_worker, self.max_attempts = workers, per_worker, max_attempts
        self.num_gpus = num_gpus  # GPU actors (Roken rollouts on a GPU cluster)
        self.log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
        self.actors: list = []
        self.retries = 0
        self.names: list[str] = []
        self.startup_seconds = 0.0  # creating the actors until all answered
        self._started: tuple = ()
        self.on_progress = None  # f(items finished in units still running, summed over actors), polled

    def describe(self) -> str:
        return f"Ray, {self.workers} actor(s): {', '.join(self.names)}"

    def publish(self, value, version: int) -> Shared:
        """One object-store copy of `value` (GRPO's weights) that units carry by reference."""
        return Shared(version, ref=[ray.put(value)])

    def _start(self, fn_ref: str, ctx: dict) -> None:
        t0 = time.perf_counter()
        self._started = (fn_ref, ctx)  # held, so the ctx's identity cannot be reused
        self.ctx_box = [ray.put(ctx)]  # one copy in the object store, shared by every actor
        self.actors = [UnitWorker.options(scheduling_strategy="SPREAD", num_gpus=self.num_gpus).remote(fn_ref)
                       for _ in range(self.workers)]
        try:
            self.names = ray.get([a.name.remote() for a in self.actors], timeout=300)
        except GetTimeoutError:
            raise RuntimeError(f"{self.workers} workers did not start within 300 s; the cluster has "
                               f"{ray.cluster_resources().get('CPU', 0):.0f} CPUs: lower --workers") from None
        self.startup_seconds = time.perf_counter() - t0
        self.log(f"started {self.workers} Ray worker(s): {', '.join(self.names)}")

    def imap_unordered(self, fn_ref: str, ctx: dict, units: Iterable[Unit]) -> Iterator[UnitResult]:
        queue = deque((u, 1) for u in units)
        if not queue:
            return
        if not self.actors or self._started[0] != fn_ref or self._started[1] is not ctx:
            # a later call with the same function and ctx reuses the actors and their caches (GRPO's
            # iterations keep each actor's model copy); anything else starts a fresh pool
            self.shutdown()
            self._start(fn_ref, ctx)
        pending: dict = {}  # ObjectRef -> (unit, attempt, actor index, submit time)
        load = [0] * len(self.actors)
        while queue or pending:
            while queue:
                a = min(range(len(self.actors)), key=load.__getitem__)
                if load[a] >= self.per_worker:
                    break
                unit, attempt = queue.popleft()
                pending[self.actors[a].run.remote(self.ctx_box, unit)] = (unit, attempt, a)
                load[a] += 1
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=2.0 if self.on_progress else None)
            if not ready:
                self._poll_progress()
                continue
            for ref in ready:
                unit, attempt, a = pending.pop(ref)
                load[a] -= 1
                try:
                    result = ray.get(ref)
                except RETRYABLE as e:
                    if isinstance(e, ActorUnavailableError):
                        # the actor's process died and Ray is restarting it: wait until it answers again, so the
                        # retries below are not spent on calls to an actor that is still coming back
                        try:
                            ray.get(self.actors[a].name.remote(), timeout=120)
                        except Exception:  # noqa: BLE001  (still down: the retry below goes to the least loaded)
                            pass
                    reason = f"{type(e).__name__}: {str(e).splitlines()[0][:200]}"
                    if attempt < self.max_attempts:
                        self.retries += 1
                        self.log(f"unit {unit.key}: worker lost ({type(e).__name__}); retry "
                                 f"{attempt + 1}/{self.max_attempts}")
                        queue.appendleft((unit, attempt + 1))
                        continue
                    result = UnitResult(unit, error=f"worker died {attempt} times: {reason}")
                except Exception as e:  # noqa: BLE001  (e.g. a result that cannot be deserialised)
                    result = UnitResult(unit, error=f"{type(e).__name__}: {str(e).splitlines()[0][:200]}")
                result.attempts = attempt
                yield result

    def _poll_progress(self) -> None:
        """Ask every actor how many items it finished (a restarted actor counts from 0 again)."""
        try:
            counts = ray.get([a.progress.remote() for a in self.actors], timeout=10)
        except Exception:  # noqa: BLE001  (an actor restarting: report next time)
            return
        self.on_progress(sum(counts))

    def shutdown(self) -> None:
        for a in self.actors:
            ray.kill(a)
        self.actors = []



def read_ray_dataset(location: str, table: str = "episodes") -> "ray.data.Dataset":
    """The shards of a dataset folder (local path or URI) as a Ray Dataset, with the same columns and
    types as `roken.data.shards.read_table` (plain Arrow lists, no tensor extension types)."""
    from .data import fs
    from .data.shards import open_dataset

    files = open_dataset(location, table).files  # the visible shards only, never a writer's temp file
    filesystem, _ = fs.resolve(location)
    return ray.data.read_parquet(files, filesystem=filesystem)
