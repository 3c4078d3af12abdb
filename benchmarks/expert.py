"""Laplacian expert throughput on one core: batched (continuous batching) vs one team at a time.

    python benchmarks/expert.py                 # N = 4 and 8, 128 episodes, 10 episodes per map
    python benchmarks/expert.py --robots 4 --episodes 256 --batch 64

Prints, per team size: expert-only episodes/s (tasks prepared beforehand) for the batched engine and for
batch size 1, and end-to-end episodes/s (map generation + fields + task sampling + expert) with
--per-map episodes on each map, as a dataset generator runs it. Figures go in benchmarks/README.md.
"""
from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")  # one core, as the per-worker figure is meant

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from roken.eval.metrics import episode_metrics, summarize  # noqa: E402
from roken.expert.laplacian import ExpertConfig, LaplacianExpert  # noqa: E402
from roken.world.maps import MapConfig, generate_map  # noqa: E402
from roken.world.tasks import TaskConfig, sample_task  # noqa: E402


def build(n: int, episodes: int, per_map: int, mc: MapConfig, tc: TaskConfig):
    maps, tasks = {}, []
    for e in range(episodes):
        i = e // per_map
        gm = maps.get(f"train-{i:06d}") or generate_map(mc, "train", i)
        maps[gm.map_id] = gm
        tasks.append(sample_task(gm, n, tc, np.random.default_rng([9, n, e])))
    return maps, tasks


def run(maps, tasks, tc, batch):
    t0 = time.perf_counter()
    out = dict(LaplacianExpert(ExpertConfig(batch_size=batch), tc).run(tasks, maps))
    return time.perf_counter() - t0, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robots", default="4,8")
    ap.add_argument("--episodes", type=int, default=128)
    ap.add_argument("--single-episodes", type=int, default=16, help="episodes for the batch-size-1 run")
    ap.add_argument("--per-map", type=int, default=10)
    ap.add_argument("--batch", type=int, default=64)
    args = ap.parse_args()
    mc, tc = MapConfig(), TaskConfig()
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}, "
          f"numpy {np.__version__}, 1 thread")
    head = f"{'N':>3}{'episodes':>10}{'steps/ep':>10}{'batched ep/s':>14}{'single ep/s':>13}{'speed-up':>10}" \
           f"{'end-to-end ep/s':>17}{'full succ':>11}"
    lines = [head, "-" * len(head)]
    for n in [int(x) for x in args.robots.split(",")]:
        t0 = time.perf_counter()
        maps, tasks = build(n, args.episodes, args.per_map, mc, tc)
        setup = time.perf_counter() - t0
        dt, out = run(maps, tasks, tc, args.batch)
        k = min(args.single_episodes, len(tasks))
        dt1, _ = run(maps, tasks[:k], tc, 1)
        steps = np.mean([ep.steps for ep in out.values()])
        rows = [episode_metrics(out[i].positions, maps[t.map_id], t.goal, t.leader, tc) for i, t in enumerate(tasks)]
        s = summarize(rows)
        b, single = len(tasks) / dt, k / dt1
        e2e = len(tasks) / (dt + setup)
        lines.append(f"{n:>3}{len(tasks):>10}{steps:>10.0f}{b:>14.1f}{single:>13.1f}{b / single:>10.1f}"
                     f"{e2e:>17.1f}{s['full_success']:>11.3f}")
        print(lines[-1], flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
