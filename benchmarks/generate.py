"""Dataset generation throughput: in-process vs Ray with 1 and 2 workers, and Ray's overhead per unit.

    python benchmarks/generate.py                      # 120 train maps x 10 episodes, 20 maps per unit
    python benchmarks/generate.py --maps 80 --workers 1,2,4

Each configuration runs the real pipeline (roken.data.build.build_dataset: maps, tasks, expert, scoring,
Parquet shards) into a fresh folder on one local Ray cluster started once (its start is reported apart).
Printed per run: wall time, episodes/s end to end and in steady state (without creating the actors), the
mean time of a unit inside its worker, and per unit the time workers sat idle:
  idle/unit = (workers x steady wall - sum of unit times) / units
With one worker, idle time is Ray's own cost (scheduling, transfer of the unit and its summary); with more,
it also holds the tail where one worker finishes its last unit while the other has none left.
Ray's overhead per unit = idle/unit of the 1-worker run + the slow-down of a unit inside a Ray worker
compared with the same unit in-process, as a share of the in-process unit time.
Parallel efficiency = throughput(k workers) / (k x throughput(1 worker)), from the same run.
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")  # one BLAS thread per process: a worker is one core

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from roken import ray_pool  # noqa: E402
from roken.config import load_config  # noqa: E402
from roken.data.build import build_dataset  # noqa: E402
from roken.units import InProcessRunner  # noqa: E402


def one_run(cfg, runner, label: str) -> dict:
    out = tempfile.mkdtemp(prefix="roken-bench-")
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            t0 = time.perf_counter()
            m = build_dataset(cfg, out, runner)
            wall = time.perf_counter() - t0
    finally:
        shutil.rmtree(out, ignore_errors=True)
    th = m["throughput"]
    startup = getattr(runner, "startup_seconds", 0.0)
    steady = wall - startup
    k = max(runner.workers, 1)
    units = len(m["shards"])
    return {"label": label, "workers": runner.workers, "wall": wall, "startup": startup,
            "episodes": th["episodes_run"], "eps": th["episodes_run"] / wall,
            "steady_eps": th["episodes_run"] / steady, "unit_s": th["worker_seconds"],
            "overhead_unit": (k * steady - th["worker_seconds"]) / units, "mean_unit": th["worker_seconds"] / units,
            "success": sum(v["success"] for v in m["by_team_size"].values()) / max(th["episodes_run"], 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--maps", type=int, default=120)
    ap.add_argument("--episodes-per-map", type=int, default=10)
    ap.add_argument("--maps-per-unit", type=int, default=20)
    ap.add_argument("--workers", default="1,2", help="Ray worker counts to run, e.g. 1,2")
    ap.add_argument("--cpus", type=int, default=os.cpu_count())
    args = ap.parse_args()
    cfg = load_config(None, [f"dataset.num_maps={args.maps}", f"dataset.episodes_per_map={args.episodes_per_map}",
                             f"dataset.maps_per_unit={args.maps_per_unit}"])
    counts = [int(w) for w in args.workers.split(",")]
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"{args.maps} train maps x {args.episodes_per_map} episodes, {args.maps_per_unit} maps per unit")
    runs = [one_run(cfg, InProcessRunner(), "in-process")]
    t0 = time.perf_counter()
    ray_pool.connect(local=True, num_cpus=args.cpus, code_root=str(ROOT))
    cluster_start = time.perf_counter() - t0
    quiet = lambda msg: None  # noqa: E731
    for k in counts:
        runs.append(one_run(cfg, ray_pool.RayRunner(k, log=quiet), f"ray x{k}"))
    print(f"local Ray cluster start: {cluster_start:.1f} s (not in the figures below)")
    head = (f"{'run':<12}{'episodes':>9}{'wall s':>8}{'actors s':>9}{'ep/s':>8}{'steady ep/s':>13}"
            f"{'unit s':>8}{'idle/unit':>11}{'idle %':>8}{'success':>9}")
    print(head)
    print("-" * len(head))
    for r in runs:
        print(f"{r['label']:<12}{r['episodes']:>9d}{r['wall']:>8.1f}{r['startup']:>9.2f}{r['eps']:>8.1f}"
              f"{r['steady_eps']:>13.1f}{r['mean_unit']:>8.2f}{r['overhead_unit'] * 1000:>9.0f}ms"
              f"{100 * r['overhead_unit'] / r['mean_unit']:>7.1f}%{r['success']:>9.3f}")
    one = next((r for r in runs if r["workers"] == 1), None)
    if one:
        for r in runs:
            if r["workers"] > 1:
                print(f"parallel efficiency 1 -> {r['workers']} workers: steady "
                      f"{r['steady_eps'] / (r['workers'] * one['steady_eps']):.3f}, end to end "
                      f"{r['eps'] / (r['workers'] * one['eps']):.3f}")
        base = runs[0]
        slow = one["mean_unit"] / base["mean_unit"] - 1
        print(f"Ray overhead per unit: {one['overhead_unit'] * 1000:.0f} ms idle between units + "
              f"{100 * slow:.1f}% slower unit inside a Ray worker = "
              f"{100 * (one['overhead_unit'] / base['mean_unit'] + slow):.1f}% of the expert's own time "
              f"({base['mean_unit']:.2f} s per unit in-process)")


if __name__ == "__main__":
    main()
