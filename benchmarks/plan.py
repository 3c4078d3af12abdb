"""Roken as a planner: plan latency and closed-loop evaluation throughput.

    python benchmarks/plan.py                                  # CPU, small + paper presets, all threads
    python benchmarks/plan.py --threads 2 --presets paper
    python benchmarks/plan.py --device cuda --dtype bf16        # GPU
    python benchmarks/plan.py --rollout-only --checkpoint models/roken-small-mixed
    python benchmarks/plan.py --latency-only --threads 1 --presets small      # guided vs unguided
    python benchmarks/plan.py --verify-only --threads 1                       # verified selection's cost
    python benchmarks/plan.py --controller-only --threads 1                   # the deployable planner per re-plan

Latency: one plan = the condition (roken.data.condition), map encoding and DDIM-10 for all robots, 1 or 32
candidates in one batch, through RokenPlanner.sample (random weights: the cost does not depend on them);
median over repeats after warm-up; `guided` rows add constraint-guided sampling (roken/plan/guidance.py) with
the schedule shown: the guided DDIM steps (plan.guide_steps), the descent iterations at each of them but the
last (plan.guide_iters) and at the last (plan.guide_final_iters); `default` = the config's defaults, `10x50` = the
first implementation's schedule; the known-map fields are computed once per episode and not timed. Throughput: closed-loop episodes/s of the shipped model on the same
evaluation tasks with continuous batching (plan.batch_size episodes per model call) vs one episode at a time.
Verification: verified selection's check of G candidates (4 robots, H = 16) on the known map, at the plan's
points and, with plan.verify_steps, at every simulator step of the executed moves (rollout.executed_points); G = 9
is G = 8 with the last plan carried as one more candidate (plan.keep_previous).
Controller: what a robot waits for with the deployable planner for user code (roken.plan.RokenController, the
shipped model with configs/deploy.yaml): the start of a task (the known map's free-space fields, once per task)
and each re-plan (guided sampling of G candidates, verification at every executed step, geodesic ranking, the
carried plan), one team at a time on `eval` tasks driven by Team.step; N = 10 plans in clusters of 4.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from roken.config import load_config
from roken.data.condition import build_condition
from roken.data.samples import SampleConfig
from roken.eval.harness import make_tasks
from roken.model.diffusion import DiffusionConfig, NoiseSchedule
from roken.model.dit import RokenDiT, preset
from roken.plan import PlanConfig, RokenPlanner, RokenRollout
from roken.world.maps import MapConfig, generate_map


def latency(planner: RokenPlanner, n: int, G: int, repeat: int, rng, guided: bool = False,
            schedule: list[str] = ()) -> float:
    from roken.plan.guidance import Guide, known_fields

    cfg = load_config(None, ["plan.guide=true", *schedule])
    occ = generate_map(MapConfig(), "eval", 0).occupancy
    free = np.argwhere(occ == 0)
    goal = free[0][::-1] + 0.5
    fields = known_fields(occ, goal) if guided else None
    times = []
    for r in range(repeat + 2):
        starts = free[rng.choice(len(free), size=n, replace=False)][:, ::-1] + 0.5
        t0 = time.perf_counter()
        cond = build_condition(occ, starts, 0, goal, planner.cfg, tokens=n)
        guide = None
        if guided:
            real = cond["robot_mask"][None] > 0
            guide = Guide(cfg.plan, cfg.task, planner.cfg, cond["start"][None], real, real, np.array([0]),
                          fields[0][None], fields[1][None], G, planner.device)
        planner.sample([cond], G, "ddim", 10, guide=guide, guide_steps=cfg.plan.guide_steps)
        if planner.device.type == "cuda":
            torch.cuda.synchronize()
        if r >= 2:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def verify_cost(G: int, repeat: int, rng, steps: bool) -> float:
    """Seconds to count the violations of G candidate plans of 4 robots on the known map (one re-plan)."""
    from roken.plan.rollout import executed_points
    from roken.plan.select import violations
    from roken.world.geometry import pad_for_clearance

    cfg = load_config(None, [])
    occ = generate_map(MapConfig(), "eval", 0).occupancy
    padded, tc = pad_for_clearance(occ), cfg.task
    free = np.argwhere(occ == 0)
    times = []
    for r in range(repeat + 2):
        q = free[rng.choice(len(free), size=4, replace=False)][:, ::-1] + 0.5
        cand = q[None, :, None] + np.cumsum(rng.normal(0, 0.3, (G, 4, 16, 2)), axis=2)
        t0 = time.perf_counter()
        paths = np.concatenate([np.broadcast_to(q[None, :, None], (G, 4, 1, 2)), cand], axis=2)
        viol = violations(paths, padded, None, tc.d_obs_min, tc.d_coll_min, tc.comm_radius)
        if steps:
            ex = executed_points(q, cand, PlanConfig().replan_every, SampleConfig().interval, tc.max_step)
            viol = viol + violations(ex, padded, None, tc.d_obs_min, tc.d_coll_min, tc.comm_radius)
        if r >= 2:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def throughput(checkpoint: str, episodes: int, batch: int, device: str) -> float:
    cfg = load_config(None, [f"eval.episodes={episodes}"])
    maps = [generate_map(cfg.map, "eval", i) for i in range(episodes)]
    tasks, _ = make_tasks(cfg, maps, 4)
    planner = RokenPlanner.load(checkpoint, device)
    ro = RokenRollout(planner, PlanConfig(batch_size=batch, device=device), cfg.task, cfg.expert)
    t0 = time.perf_counter()
    steps = sum(len(p) - 1 for _, p, _ in ro.run([t for _, t in tasks], {m.map_id: m for m in maps}))
    dt = time.perf_counter() - t0
    print(f"  batch {batch:>3}: {len(tasks)} episodes ({steps} simulator steps) in {dt:.1f} s = "
          f"{len(tasks) / dt:.2f} episodes/s, {steps / dt:.0f} steps/s")
    return len(tasks) / dt


def controller_latency(checkpoint: str, config: str, tasks_per_n: int, device: str) -> None:
    from roken.plan import RokenController

    print(f"deployable planner ({checkpoint}, {config}), one team at a time, {tasks_per_n} `eval` tasks per row:")
    print(f"{'robots':>7}{'clusters':>10}{'start (ms)':>12}{'re-plans':>10}{'median ms':>11}{'p90 ms':>8}{'max ms':>8}")
    for n, cluster in ((4, 0), (10, 4)):
        ctl = RokenController.load(checkpoint, config, overrides=[f"plan.cluster_size={cluster}"], device=device)
        cfg = load_config(config, [f"eval.episodes={tasks_per_n}"])
        maps = {m.map_id: m for m in (generate_map(cfg.map, "eval", i) for i in range(tasks_per_n))}
        starts, times = [], []
        for _, task in make_tasks(cfg, list(maps.values()), n)[0]:
            t0 = time.perf_counter()
            team = ctl.start(maps[task.map_id].occupancy, task.starts, task.leader, task.goal, seed=task.seed)
            starts.append(time.perf_counter() - t0)
            while not team.finished:
                t0 = time.perf_counter()
                team.replan()
                times.append(time.perf_counter() - t0)
                team.step()
        ms = np.array(times) * 1e3
        print(f"{n:>7}{cluster or '-':>10}{statistics.median(starts) * 1e3:>12.0f}{len(ms):>10}{np.median(ms):>11.0f}"
              f"{np.percentile(ms, 90):>8.0f}{ms.max():>8.0f}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", default="small,paper")
    p.add_argument("--device", default="cpu")
    p.add_argument("--dtype", default="fp32", choices=["fp32", "bf16"])
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--checkpoint", default="models/roken-small-mixed")
    p.add_argument("--episodes", type=int, default=16, help="closed-loop episodes (4 robots)")
    p.add_argument("--rollout-only", action="store_true")
    p.add_argument("--latency-only", action="store_true")
    p.add_argument("--verify-only", action="store_true", help="only the cost of verified selection")
    p.add_argument("--controller-only", action="store_true", help="only the deployable planner's per-re-plan latency")
    p.add_argument("--deploy-checkpoint", default="models/roken-cpu-four-dagger")
    p.add_argument("--deploy-config", default="configs/deploy.yaml")
    p.add_argument("--deploy-tasks", type=int, default=10, help="tasks per team size for --controller-only")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    print(f"device {a.device}, dtype {a.dtype}, torch threads {torch.get_num_threads()}")
    if a.controller_only:
        return controller_latency(a.deploy_checkpoint, a.deploy_config, a.deploy_tasks, a.device)
    rng = np.random.default_rng(0)
    if not a.rollout_only:
        print(f"{'verified selection, 4 robots':<30}{'candidates':>11}{'ms / re-plan':>14}")
        for G in (1, 8, 9, 32):  # 9: G = 8 and the carried plan of plan.keep_previous
            for steps in (False, True):
                ms = verify_cost(G, max(a.repeat, 20), rng, steps) * 1e3
                print(f"{'points + executed steps' if steps else 'planned points':<30}{G:>11}{ms:>14.2f}")
    if a.verify_only:
        return
    if not a.rollout_only:
        print(f"{'preset':<8}{'robots':>7}{'candidates':>11}{'guided':>10}{'ms / plan (DDIM-10)':>22}")
        old = ["plan.guide_steps=10", "plan.guide_iters=50", "plan.guide_final_iters=0"]
        for name in a.presets.split(","):
            model = RokenDiT(preset(name)).to(a.device)
            planner = RokenPlanner(model, NoiseSchedule(DiffusionConfig(), a.device), SampleConfig(), a.device, a.dtype)
            for n, G, guided in ((4, 1, "no"), (4, 8, "no"), (4, 32, "no"), (10, 1, "no"), (10, 32, "no"),
                                 (4, 1, "default"), (4, 8, "default"), (4, 1, "10x50"), (4, 8, "10x50")):
                ms = latency(planner, n, G, a.repeat, rng, guided != "no", old if guided == "10x50" else []) * 1e3
                print(f"{name:<8}{n:>7}{G:>11}{guided:>10}{ms:>22.1f}")
    if a.latency_only:
        return
    print(f"closed loop, {a.checkpoint}, 4 robots, DDIM-10, replan every 2:")
    one = throughput(a.checkpoint, a.episodes, 1, a.device)
    many = throughput(a.checkpoint, a.episodes, 64, a.device)
    print(f"  continuous batching speed-up: {many / one:.1f}x")


if __name__ == "__main__":
    main()
