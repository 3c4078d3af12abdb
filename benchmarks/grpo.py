"""GRPO post-training: rollout and learner throughput, and rollout scaling over Ray actors.

    python benchmarks/grpo.py --data data/train500                      # CPU, 1 thread per actor, 1 -> 2 actors
    python benchmarks/grpo.py --data data/train500 --device cuda --no-ray  # GPU rollout and learner

Rollout: candidates/s of one worker (a group = one prompt x G candidates through the full DDPM chain, the
trained transitions recorded, the privileged reward scored). Learner: trained transitions/s (forward of the
policy and the reference, backward, optimizer) over the same groups. Scaling: the same prompts on 1 and on 2
Ray actors of a private local cluster (roken.ray_pool.RayRunner, the post-training path), efficiency =
rate(2) / (2 rate(1)).
"""
from __future__ import annotations

import argparse
import copy
import os
import time
from dataclasses import asdict

os.environ.setdefault("RAY_AUTH_MODE", "token")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from roken.plan.planner import RokenPlanner  # noqa: E402
from roken.rl.config import RLConfig  # noqa: E402
from roken.rl.grpo import Learner  # noqa: E402
from roken.rl.prompts import PromptSource, condition  # noqa: E402
from roken.rl.rollout import RolloutWorker  # noqa: E402
from roken.units import Shared, Unit  # noqa: E402
from roken.world.tasks import TaskConfig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="models/roken-small-mixed")
    ap.add_argument("--data", default="data/train500")
    ap.add_argument("--prompts", type=int, default=8)
    ap.add_argument("--group-size", type=int, default=32)
    ap.add_argument("--transitions", type=int, default=10)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the in-process measurements")
    ap.add_argument("--no-ray", action="store_true", help="skip the 1 -> 2 actor scaling")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    rc = RLConfig(group_size=args.group_size, train_transitions=args.transitions, minibatch_prompts=4)
    tc = TaskConfig()
    blob = RokenPlanner.pack(args.checkpoint)
    worker = RolloutWorker(blob, args.data, tc, rc, args.device)
    worker.set_weights(Shared(0, value={k: v.cpu() for k, v in worker.model.state_dict().items()}))
    prompts = PromptSource(worker.bank, tc, rc.min_future, [4]).draw(np.random.default_rng(0), args.prompts)
    worker.group(prompts[0])  # warm-up
    t0 = time.perf_counter()
    groups = [worker.group(p) for p in prompts]
    roll = time.perf_counter() - t0
    cand_rate = len(groups) * rc.group_size / roll
    pl = RokenPlanner.unpack(blob, args.device)
    learner = Learner(pl.model, copy.deepcopy(pl.model), pl.schedule, rc, pl.device)
    conds = [condition(worker.bank, g.prompt, pl.cfg) for g in groups]
    for g in groups:  # every group counts, whatever its rewards: the cost does not depend on them
        g.rewards = np.random.default_rng(0).normal(size=rc.group_size).astype(np.float32)
    t0 = time.perf_counter()
    learner.update(groups, conds, torch.Generator().manual_seed(0))
    learn = time.perf_counter() - t0
    trans = len(groups) * rc.group_size * len(groups[0].steps)
    print(f"model {blob['path']} ({pl.model.num_params() / 1e6:.2f}M params), {args.device}, {args.threads} thread(s); "
          f"{len(groups)} prompts x G={rc.group_size}, {len(groups[0].steps)} trained transitions, DDPM "
          f"{pl.schedule.K} steps")
    print(f"{'stage':34s} {'seconds':>8s} {'rate':>22s}")
    print(f"{'rollout (one worker)':34s} {roll:8.2f} {cand_rate:14.1f} cand/s")
    print(f"{'learner (policy + reference)':34s} {learn:8.2f} {trans / learn:14.0f} trans/s")
    print(f"{'time split rollout : learn':34s} {'':8s} {f'{roll / (roll + learn):.2f} : {learn / (roll + learn):.2f}':>22s}")
    if args.no_ray:
        return
    from roken import ray_pool

    ray_pool.connect(local=True, num_cpus=2, code_root=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    ctx = {"checkpoint": blob, "data": os.path.abspath(args.data), "task": asdict(tc), "rl": asdict(rc),
           "device": "cpu"}
    rates = {}
    for n in (1, 2):
        runner = ray_pool.RayRunner(n)
        weights = runner.publish({k: v.cpu() for k, v in pl.model.state_dict().items()}, 0)
        warm = [Unit(f"w{j}", {"prompts": [prompts[j]], "weights": weights}) for j in range(n)]
        list(runner.imap_unordered("roken.rl.rollout:rollout_unit", ctx, warm))  # start, load, first call
        units = [Unit(f"u{j}", {"prompts": [p], "weights": weights}) for j, p in enumerate(prompts)]
        t0 = time.perf_counter()
        got = sum(len(r.value) for r in runner.imap_unordered("roken.rl.rollout:rollout_unit", ctx, units))
        rates[n] = got * rc.group_size / (time.perf_counter() - t0)
        runner.shutdown()
        print(f"{f'Ray, {n} rollout actor(s)':34s} {'':8s} {rates[n]:14.1f} cand/s")
    print(f"{'parallel efficiency 1 -> 2 actors':34s} {'':8s} {rates[2] / (2 * rates[1]):22.2f}")


if __name__ == "__main__":
    main()
