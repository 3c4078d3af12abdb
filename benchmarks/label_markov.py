"""How much of the expert's chunk label is a function of what the model sees? Restart the expert at recorded states.

    python benchmarks/label_markov.py                         # 40 eval tasks, N = 4, 6 states each, one thread
    python benchmarks/label_markov.py --episodes 100 --robots 6

A Roken sample conditions on the team's positions, the goal and the map; its target is the next 16 chunk points
of the recorded expert episode. The Laplacian expert also carries hidden state: the inertia of its previous step,
the spanning tree kept with hysteresis, the progress along its reference path, its stall counters and the
smoothing of the recorded trajectory. Here the expert runs each task whole, then restarts from states of its own
episode (same positions, goal and map; fresh hidden state) and the two futures are compared point by point. The
distance over the first `plan.replan_every` points is in the units of the training validation's
`val/l2_executed_m`, so it reads against a model's figure and `benchmarks/plain_tolerance.py`'s sigma: what part of
a model's executed-move error a model could not remove while the labels keep the hidden state
(`dataset.restart_every` makes labels the restarted expert's, README "Markov labels").
"""
from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import numpy as np
import torch

from roken.config import load_config
from roken.eval.harness import load_maps, make_tasks
from roken.expert.laplacian import LaplacianExpert
from roken.world.tasks import Task, check_start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--maps", default="eval")
    ap.add_argument("--states", type=int, default=6, help="restart states per episode, drawn uniformly")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = load_config(None, [f"eval.maps={args.maps}", f"eval.episodes={args.episodes}"])
    maps, _ = load_maps(cfg)
    by_id = {m.map_id: m for m in maps}
    tasks = [t for _, t in make_tasks(cfg, maps, args.robots)[0]]
    tc, H, I, E = cfg.task, cfg.samples.horizon, cfg.samples.interval, cfg.plan.replan_every
    t0 = time.perf_counter()
    recorded = dict(LaplacianExpert(cfg.expert, tc).run(tasks, by_id))
    rng = np.random.default_rng(args.seed)
    starts, labels = [], []
    for i, t in enumerate(tasks):
        P = recorded[i].positions.astype(np.float64)
        span = max(len(P) - H * I, 1)
        for s in rng.choice(span, size=min(args.states, span), replace=False):
            if check_start(by_id[t.map_id], P[s], tc) is None:
                starts.append(Task(t.map_id, P[s].copy(), t.goal, t.leader, seed=t.seed))
                labels.append(P[np.minimum(s + I * np.arange(1, H + 1), len(P) - 1)])  # (H, N, 2)
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}, numpy "
          f"{np.__version__}, 1 thread; {len(tasks)} `{args.maps}` tasks, N = {args.robots}, {len(starts)} restart "
          f"states; chunk points every {I} steps, the first {E} executed per re-plan")
    head = f"{'restarted expert':<38}{'executed L2':>12}{'median':>8}{'leader':>8}{'followers':>10}" \
           f"{'point 4':>9}{'point 16':>9}{'move 1':>8}"
    print(head + "\n" + "-" * len(head))
    move1 = np.mean([np.linalg.norm(lab[0] - s.starts, axis=-1).mean() for lab, s in zip(labels, starts)])
    print(f"{'(the recorded expert)':<38}{'':>12}{'':>8}{'':>8}{'':>10}{'':>9}{'':>9}{move1:>8.3f}")
    for name, smooth, warm in (("from rest, as recorded (smoothing 5)", cfg.expert.smooth_window, False),
                               ("from rest, without smoothing", 1, False),
                               ("warm start (expert.warm_start)", cfg.expert.smooth_window, True)):
        ec = dataclasses.replace(cfg.expert, step_limit_factor=0.0, step_limit_extra=H * I, smooth_window=smooth,
                                 warm_start=warm)
        again = dict(LaplacianExpert(ec, tc).run(starts, by_id))
        d = []
        for j, lab in enumerate(labels):
            Q = again[j].positions.astype(np.float64)
            d.append(np.linalg.norm(Q[np.minimum(I * np.arange(1, H + 1), len(Q) - 1)] - lab, axis=-1))  # (H, N)
        d = np.stack(d)  # (S, H, N)
        lead = np.zeros(d.shape[::2], bool)
        lead[np.arange(len(starts)), [s.leader for s in starts]] = True  # (S, N)
        ex = d[:, :E].mean(1)  # (S, N)
        first = np.mean([np.linalg.norm(again[j].positions[min(I, len(again[j].positions) - 1)] - s.starts,
                                        axis=-1).mean() for j, s in enumerate(starts)])
        print(f"{name:<38}{ex.mean():>12.3f}{np.median(d[:, :E]):>8.3f}{ex[lead].mean():>8.3f}{ex[~lead].mean():>10.3f}"
              f"{d[:, 3].mean():>9.3f}{d[:, H - 1].mean():>9.3f}{first:>8.3f}")
    print(f"({time.perf_counter() - t0:.0f} s) distances in metres between the recorded and the restarted expert's "
          f"chunk points, mean over robots and states; move 1: mean length of the first chunk move")


if __name__ == "__main__":
    main()
