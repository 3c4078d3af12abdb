"""How precise must a plain chunk planner's executed moves be? The expert as a chunk planner with a known error.

    python benchmarks/plain_tolerance.py                                   # 100 eval tasks, N = 4, one thread
    python benchmarks/plain_tolerance.py --episodes 200 --sigmas 0,0.1,0.2,0.4,0.8 --errors independent,offset
    python benchmarks/plain_tolerance.py --sigmas 0,0.45 --errors offset --config configs/expert/cautious.yaml

Plain Roken executes the first plan.replan_every = 2 moves of each sampled chunk, then re-plans; any robot that
comes within d_obs_min of an obstacle or d_coll_min of another robot at any simulator step fails the episode.
Here the planner is the Laplacian expert itself, restarted from the team's current state at every re-plan and run
for the executed moves' 2 x interval simulator steps; its chunk points (one every `interval` steps) get an error
of known size before they are executed exactly as the Roken rollout executes a plan (rollout.step_toward, clipped
at max_step). So each row answers: with executed-move error sigma, what full success could a plain chunk planner
reach on these tasks at best? sigma is in the units of the training validation's `val/l2_executed_m` (the mean
distance of the executed points to the expert's, per robot and point), so a model's open-loop figure reads
straight across (the shipped models: 0.73-0.83 m on held-out expert states, README "Training on a CPU").

Errors: `independent` draws each robot's error at each executed point afresh (N(0, s^2 I), s = sigma / sqrt(pi / 2),
so E|e| = sigma); `offset` draws one error per robot and re-plan and adds it to both points (a biased plan, as a
model's errors are: sampling at temperature ~0 does not remove them, README "Why plain Roken fails"). The draws
are common across sigmas (one unit-normal stream per episode, scaled), so rows differ only by sigma. An episode
stops at its first violation (it has failed; the expert cannot start from there). sigma = 0 measures the expert
restarted every 8 steps (its tree and inertia start afresh), the ceiling of this construction.
"""
from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import numpy as np
import torch

from roken.config import load_config
from roken.dagger.relabel import feasible_steps
from roken.eval.harness import load_maps, make_tasks
from roken.eval.metrics import COMPACT_HEAD, compact_cells, summarize
from roken.expert.laplacian import LaplacianExpert
from roken.plan.rollout import step_toward
from roken.world.metrics import episode_metrics
from roken.world.tasks import Task, check_start


def run_sigma(cfg, tasks, maps, sigma: float, error: str, replan: int, interval: int, seed: int):
    """Closed loop of the perturbed restarted expert on tasks [(e, Task)]: (metrics rows, mean executed error)."""
    tc = cfg.task
    limits = LaplacianExpert(cfg.expert, tc)
    seg = LaplacianExpert(dataclasses.replace(cfg.expert, step_limit_factor=0.0, step_limit_extra=replan * interval,
                                              smooth_window=1), tc)
    s = sigma / np.sqrt(np.pi / 2)
    state = []
    for e, t in tasks:
        q = np.asarray(t.starts, np.float64)
        state.append({"t": t, "q": q, "hist": [q.astype(np.float32)], "limit": limits.step_limit(t, maps[t.map_id]),
                      "rng": np.random.default_rng([seed, e]), "done": False, "reached": False})
    errs = []
    while True:
        live = [st for st in state if not st["done"]]
        if not live:
            break
        starts = [Task(st["t"].map_id, st["q"].copy(), st["t"].goal, st["t"].leader, seed=st["t"].seed) for st in live]
        ok = [check_start(maps[t.map_id], t.starts, tc) is None for t in starts]
        for st, good in zip(live, ok):
            st["done"] |= not good
        run = [i for i, good in enumerate(ok) if good]
        segs = dict(seg.run([starts[i] for i in run], maps)) if run else {}
        for j, i in enumerate(run):
            st, pos = live[i], segs[j].positions.astype(np.float64)
            n = pos.shape[1]
            pts = np.stack([pos[min((k + 1) * interval, len(pos) - 1)] for k in range(replan)], 1)  # (n, replan, 2)
            z = st["rng"].standard_normal((n, replan, 2)) if error == "independent" else \
                np.repeat(st["rng"].standard_normal((n, 1, 2)), replan, axis=1)
            plan = pts + s * z
            errs.append(np.linalg.norm(plan - pts, axis=-1).mean())
            prev = st["q"].copy()
            goal, leader = np.asarray(st["t"].goal, np.float64), st["t"].leader
            for k in range(replan):  # exactly as rollout._Slot.execute
                for m in range(1, interval + 1):
                    step = step_toward(st["q"], prev, plan[:, k], m, interval, tc.max_step)
                    st["hist"].append((st["q"] + step).astype(np.float32))
                    st["q"] = st["hist"][-1].astype(np.float64)
                    if np.linalg.norm(st["hist"][-1][leader].astype(np.float64) - goal) <= tc.eps_goal:
                        st["reached"] = True
                    if st["reached"] or len(st["hist"]) - 1 >= st["limit"]:
                        st["done"] = True
                        break
                if st["done"]:
                    break
                prev = plan[:, k]
            if not feasible_steps(np.asarray(st["hist"][-replan * interval:]), maps[st["t"].map_id], tc).all():
                st["done"] = True  # a violation: the episode has failed, and the expert cannot start there
    rows = [episode_metrics(np.asarray(st["hist"]), maps[st["t"].map_id], np.asarray(st["t"].goal), st["t"].leader,
                            tc) for st in state]
    return rows, float(np.mean(errs)) if errs else 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--maps", default="eval")
    ap.add_argument("--sigmas", default="0,0.1,0.2,0.4,0.8")
    ap.add_argument("--errors", default="independent,offset")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", help="YAML config whose sections override the defaults (e.g. configs/expert/cautious.yaml)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, e.g. expert.margin_obs=0.4 (a more cautious expert's tolerance)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = load_config(args.config, [f"eval.maps={args.maps}", f"eval.episodes={args.episodes}", *args.set])
    maps, _ = load_maps(cfg)
    tasks, skipped = make_tasks(cfg, maps, args.robots)
    by_id = {m.map_id: m for m in maps}
    replan, interval = cfg.plan.replan_every, cfg.samples.interval
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}, numpy "
          f"{np.__version__}, 1 thread; {len(tasks)} `{args.maps}` tasks (the harness's, seed {cfg.eval.seed}), "
          f"N = {args.robots}, {replan} moves of {interval} steps executed per re-plan")
    head = f"{'error':>12}{'sigma':>7}{'measured':>10}{COMPACT_HEAD}{'s':>7}"
    lines = [head, "-" * len(head)]
    print(head, flush=True)
    for error in args.errors.split(","):
        for sigma in [float(x) for x in args.sigmas.split(",")]:
            if sigma == 0 and error != args.errors.split(",")[0]:
                continue  # one sigma = 0 row: the error's form does not matter there
            t0 = time.perf_counter()
            rows, measured = run_sigma(cfg, tasks, by_id, sigma, error, replan, interval, args.seed)
            m = summarize(rows)
            lines.append(f"{error:>12}{sigma:>7.2f}{measured:>10.3f}{compact_cells(m)}{time.perf_counter() - t0:>7.0f}")
            print(lines[-1], flush=True)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
