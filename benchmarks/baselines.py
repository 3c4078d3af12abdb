"""Closed-loop throughput of the model-free planners: the Laplacian expert and the SGG and GNN baselines.

    python benchmarks/baselines.py                      # 64 evaluation tasks, N = 4, one thread
    python benchmarks/baselines.py --episodes 128 --robots 8

Episodes/s per core on the same evaluation tasks (eval split, seed 0), each planner batched as the harness runs
it (expert.batch_size / sgg.batch_size slots with continuous batching); the GNN scorer is models/gnn-scorer.
Target (issue 20): SGG >= 5 episodes/s per core at N = 4.
"""
from __future__ import annotations

import argparse
import time

import torch

from roken.config import load_config
from roken.eval.harness import make_tasks
from roken.expert.gnn import GNNPlanner
from roken.expert.laplacian import LaplacianExpert
from roken.expert.sgg import SGGPlanner
from roken.world.maps import generate_map


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--robots", type=int, default=4)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    cfg = load_config(None, [f"eval.episodes={a.episodes}"])
    maps = [generate_map(cfg.map, "eval", i) for i in range(a.episodes)]
    tasks, _ = make_tasks(cfg, maps, a.robots)
    by_id = {m.map_id: m for m in maps}
    planners = {"laplacian": LaplacianExpert(cfg.expert, cfg.task),
                "sgg": SGGPlanner(cfg.sgg, cfg.task, cfg.expert),
                "gnn": GNNPlanner.load(cfg.gnn, cfg.sgg, cfg.task, cfg.expert)}
    print(f"{len(tasks)} evaluation tasks, N = {a.robots}, {a.threads} thread(s)")
    print(f"{'planner':<10}{'episodes/s':>12}{'steps/s':>10}{'seconds':>9}")
    for name, pl in planners.items():
        t0 = time.perf_counter()
        steps = 0
        for item in pl.run([t for _, t in tasks], by_id):  # (i, ExpertEpisode) or (i, positions, info)
            pos = item[1].positions if name == "laplacian" else item[1]
            steps += len(pos) - 1
        dt = time.perf_counter() - t0
        print(f"{name:<10}{len(tasks) / dt:>12.2f}{steps / dt:>10.0f}{dt:>9.1f}")


if __name__ == "__main__":
    main()
