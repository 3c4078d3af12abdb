"""GRPO post-training, the driver (paper appendix): per iteration the learner publishes its weights once (a
version), rollout workers sample a group per prompt, the learner runs its epochs over that on-policy buffer, and
the buffer is discarded. Runs without Ray on `InProcessRunner` (--workers 0), or with rollout actors on
`roken.ray_pool.RayRunner` (a killed actor is restarted by Ray and its unit re-queued, so no group is lost or
counted twice; a group sampled with an older version is dropped and counted).

Checkpoints are pretraining's format (model.safetensors + config.json + train_state.pt), so the planner and
evaluate.py load a post-trained model the same way; running the same command again resumes at the saved
iteration.
"""
from __future__ import annotations

import copy
import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ..data.build import code_version
from ..data.samples import EpisodeBank
from ..data.store import atomic_write_json
from ..plan.planner import RokenPlanner
from ..train import checkpoint as ckpt
from ..train.data import fingerprint
from ..train.logger import RunLogger, duration
from ..devices import pick_device
from ..units import Unit
from ..world.tasks import TaskConfig
from .config import RLConfig, check, team_sizes
from .grpo import Learner
from .hard import HardPrompts, difficulty
from .prompts import PromptSource, condition

UNIT_FN = "roken.rl.rollout:rollout_unit"
# rl keys that must match to resume a run (iterations, logging and evaluation may change)
RESUME_KEYS = ("prompts_per_iteration", "group_size", "clip", "kl_beta", "lr", "weight_decay", "grad_clip",
               "epochs", "minibatch_prompts", "train_transitions", "transitions", "skip_final", "seed",
               "w_obs", "w_inter", "w_conn", "w_goal", "w_wp", "reach_bonus", "c_max", "hard_cost",
               "reward_scale")


class PostTraining:
    def __init__(self, rc: RLConfig, tc: TaskConfig, checkpoint: str, data: str, out: str | Path, runner,
                 prompts_per_unit: int = 4, log_stream=None):
        check(rc)
        self.rc, self.tc, self.data, self.out, self.runner = rc, tc, data, Path(out), runner
        self.prompts_per_unit, self.log_stream = prompts_per_unit, log_stream
        self.blob = RokenPlanner.pack(checkpoint, task_max_step=tc.max_step)
        self.device = pick_device(rc.device)

    def _resume_point(self) -> tuple[Path | None, int]:
        found = [c for c in ckpt.list_checkpoints(self.out) if (c / ckpt.STATE).is_file()] if self.out.is_dir() else []
        if not found:
            return None, 0
        old = ckpt.read_config(found[-1])
        bad = [k for k in RESUME_KEYS if old.get("rl", {}).get(k) != getattr(self.rc, k)]
        if old.get("pretrained", {}).get("path") != self.blob["path"]:
            bad.append(f"--checkpoint (was {old.get('pretrained', {}).get('path')})")
        if bad:
            raise ValueError(f"{self.out} holds a post-training run made with other settings ({', '.join(bad[:6])}); "
                             f"its checkpoints are kept. Use a new --out, or the old settings to resume it")
        return found[-1], int(old.get("step", 0))

    def config_dict(self, iteration: int) -> dict:
        c = copy.deepcopy(self.blob["config"])
        for k in ("train", "validation"):
            c.pop(k, None)
        return c | {"rl": asdict(self.rc), "task": asdict(self.tc), "step": iteration, "kind": "roken-posttraining",
                    "pretrained": {"path": self.blob["path"], "step": self.blob["config"].get("step")},
                    "rl_dataset": fingerprint(self.data), "code_version": code_version()}

    def fit(self) -> dict:
        rc = self.rc
        planner = RokenPlanner.unpack(self.blob, str(self.device))
        policy, sched, cfg = planner.model, planner.schedule, planner.cfg
        reference = copy.deepcopy(policy)
        learner = Learner(policy, reference, sched, rc, self.device)
        bank = EpisodeBank.from_folder(self.data, cfg.canvas)
        source = PromptSource(bank, self.tc, rc.min_future, team_sizes(rc), cfg.max_robots)
        hard = HardPrompts(rc.hard_store_size, rc.hard_temperature, rc.seed)
        resume, start = self._resume_point()
        done = self.out / "summary.json"
        if resume is not None and start >= rc.iterations and done.is_file():
            return read_summary(self.out)  # a finished run: its summary as written, nothing rewritten
        if resume is not None:
            s = ckpt.load_train_state(resume)
            policy.load_state_dict(s["policy"])
            learner.opt.load_state_dict(s["optimizer"])
            hard.load_state_dict(s["hard"])
        ckpt.remove_temporaries(self.out)
        log = RunLogger(self.out, True, start, self.log_stream)
        ctx = {"checkpoint": self.blob, "data": self.data, "task": asdict(self.tc), "rl": asdict(rc),
               "device": rc.rollout_device}
        log.print(f"[posttrain] {self.blob['path']} ({policy.num_params() / 1e6:.2f}M params) on {self.device}; "
                  f"{len(source.eligible)} episodes for prompts; {rc.prompts_per_iteration} prompts x "
                  f"G={rc.group_size}, {rc.train_transitions} trained transitions each; rollouts on "
                  f"{'in-process' if self.runner.workers == 0 else f'{self.runner.workers} Ray actor(s)'}; "
                  + (f"resuming at iteration {start} from {resume}" if resume else f"iterations 0..{rc.iterations}"))
        history, t_start = [], time.perf_counter()
        self._ctx, self._bank, self._source, self._hard, self._log = ctx, bank, source, hard, log
        buf = None
        for it in range(start, rc.iterations):
            self.iteration = it  # where a Ctrl-C stopped it
            if buf is None:  # synchronous, or the first buffer of an overlapped run
                buf = self._collect(it, self._publish(policy, it))
            nxt, idle_s = None, buf["seconds"]  # synchronous: the learner waits while the buffer is sampled
            if rc.overlap and it + 1 < rc.iterations:
                # the next buffer samples with these weights (version it) while the learner moves to it + 1:
                # its groups arrive one version behind (PPO's ratio to the behaviour policy accounts for that)
                shared = self._publish(policy, it)
                with ThreadPoolExecutor(1) as pool:
                    job = pool.submit(self._learn, it, buf, learner, cfg)
                    nxt = self._collect(it + 1, shared)
                    stats = job.result()
                # the learner waits only for what is left of the next buffer when it is done
                idle_s = max(0.0, nxt["seconds"] - stats["_seconds"]) + (buf["seconds"] if it == start else 0.0)
            else:
                stats = self._learn(it, buf, learner, cfg)
            learn_s = stats.pop("_seconds")
            groups = buf["groups"]
            hard.add([g.prompt for g in groups], [difficulty(g.terms["hard"], g.rewards) for g in groups])
            metrics = stats | self._rollout_metrics(buf, it) | {
                "time/rollout_s": buf["seconds"], "time/learn_s": learn_s, "time/learner_idle_s": idle_s}
            log.log(it + 1, metrics)
            history.append(metrics)
            done = it + 1 - start
            stale = f", {buf['stale']} stale" if buf["stale"] else ""
            eta = (time.perf_counter() - t_start) / done * (rc.iterations - it - 1)
            log.print(f"[posttrain] iteration {it + 1}/{rc.iterations} reward {metrics['rollout/reward_mean']:.2f} "
                      f"(std {metrics['rollout/reward_std']:.2f}) ok {metrics['rollout/constraint_ok_frac']:.3f} "
                      f"reach {metrics['rollout/reach_frac']:.3f} | kl {stats['losses/kl_ref']:.2e} approx_kl "
                      f"{stats['losses/approx_kl']:.2e} clipfrac {stats['losses/clipfrac']:.3f} | rollout "
                      f"{buf['seconds']:.1f} s ({metrics['charts/candidates_per_s']:.1f} cand/s), learn {learn_s:.1f} s"
                      f"{stale}, ETA {duration(eta)}")
            if (it + 1) % rc.checkpoint_every == 0 or it + 1 == rc.iterations:
                self._save(it + 1, policy, learner, hard)
            buf = nxt
        self.runner.shutdown()
        log.close()
        first = history[0] if history else {}
        last = history[-1] if history else {}
        summary = {"iterations": rc.iterations, "resumed_from": start, "wall_s": time.perf_counter() - t_start,
                   "first": first, "last": last,
                   "rollout_s": sum(h["time/rollout_s"] for h in history),
                   "learn_s": sum(h["time/learn_s"] for h in history),
                   "checkpoint": str(self.out / ckpt.checkpoint_name(rc.iterations))}
        atomic_write_json(summary, self.out / "summary.json")
        return summary

    def _publish(self, policy, version: int):
        return self.runner.publish({k: v.detach().cpu().clone() for k, v in policy.state_dict().items()}, version)

    def _collect(self, it: int, shared) -> dict:
        """One buffer: the iteration's prompts (hard ones with probability rl.hard_prompt_prob) sampled by the
        rollout workers with the weights in `shared`; groups of an older version are dropped and counted."""
        rc, t0 = self.rc, time.perf_counter()
        rng = np.random.default_rng([rc.seed, it])
        n_hard = int(rng.binomial(rc.prompts_per_iteration, rc.hard_prompt_prob)) if len(self._hard) else 0
        prompts = self._hard.draw(n_hard) + self._source.draw(rng, rc.prompts_per_iteration - n_hard)
        k = self.prompts_per_unit
        units = [Unit(f"it{it:04d}-u{j // k:04d}", {"prompts": prompts[j:j + k], "weights": shared},
                      size=len(prompts[j:j + k])) for j in range(0, len(prompts), k)]
        groups, stale, failed = [], 0, 0
        for r in self.runner.imap_unordered(UNIT_FN, self._ctx, units):
            if not r.ok:
                failed += 1
                self._log.print(f"[posttrain] unit {r.unit.key} failed: {r.error}")
                continue
            for g in r.value:
                if g.version < shared.version:
                    stale += 1
                    continue
                groups.append(g)
        if not groups:
            raise RuntimeError(f"iteration {it}: every rollout unit failed (errors above)")
        groups.sort(key=lambda g: g.prompt)  # the learner's order does not depend on which actor was first
        return {"groups": groups, "stale": stale, "failed": failed, "hard": n_hard, "prompts": len(prompts),
                "version": shared.version, "seconds": time.perf_counter() - t0}

    def _learn(self, it: int, buf: dict, learner: Learner, cfg) -> dict:
        t0 = time.perf_counter()
        conds = [condition(self._bank, g.prompt, cfg) for g in buf["groups"]]
        gen = torch.Generator().manual_seed(int(np.random.SeedSequence([self.rc.seed, it, 1]).generate_state(1)[0]))
        stats = learner.update(buf["groups"], conds, gen)
        return stats | {"_seconds": time.perf_counter() - t0}

    def _rollout_metrics(self, buf: dict, it: int) -> dict:
        groups = buf["groups"]
        cat = lambda key: np.concatenate([g.terms[key] for g in groups])  # noqa: E731
        rewards = np.stack([g.rewards for g in groups])
        return {"rollout/reward_mean": float(rewards.mean()), "rollout/reward_std": float(rewards.std()),
                "rollout/constraint_ok_frac": float(1 - cat("hard").mean()),
                "rollout/obs_violation_frac": float(cat("obs").mean()),
                "rollout/inter_violation_frac": float(cat("inter").mean()),
                "rollout/disconnect_frac": float(cat("conn").mean()), "rollout/reach_frac": float(cat("reach").mean()),
                "rollout/hard_prompt_frac": buf["hard"] / max(buf["prompts"], 1), "rollout/groups": len(groups),
                "rollout/stale_groups": buf["stale"], "rollout/failed_units": buf["failed"],
                "charts/weight_version_lag": float(np.mean([it - g.version for g in groups])),
                "charts/candidates_per_s": len(groups) * self.rc.group_size / max(buf["seconds"], 1e-9)}

    def _save(self, iteration: int, policy, learner: Learner, hard: HardPrompts) -> None:
        weights = {k: v.detach().cpu().clone() for k, v in policy.state_dict().items()}
        state = {"policy": weights, "optimizer": learner.opt.state_dict(), "iteration": iteration,
                 "hard": hard.state_dict()}
        ckpt.save_atomic(self.out, iteration, weights, self.config_dict(iteration), state)
        ckpt.prune(self.out, self.rc.keep_checkpoints)


def summary_table(summary: dict) -> str:
    f, last = summary.get("first", {}), summary.get("last", {})
    keys = ("rollout/reward_mean", "rollout/constraint_ok_frac", "rollout/reach_frac", "losses/kl_ref",
            "losses/approx_kl", "losses/clipfrac")
    lines = [f"{'metric':28s} {'first':>10s} {'last':>10s}", "-" * 50]
    lines += [f"{k:28s} {f.get(k, float('nan')):10.4f} {last.get(k, float('nan')):10.4f}" for k in keys]
    total = summary["rollout_s"] + summary["learn_s"]
    lines += ["-" * 50, f"iterations {summary['resumed_from']} -> {summary['iterations']} in "
              f"{duration(summary['wall_s'])}; rollout {summary['rollout_s']:.0f} s, learn {summary['learn_s']:.0f} s "
              f"({100 * summary['learn_s'] / max(total, 1e-9):.0f}% learning)", f"checkpoint: {summary['checkpoint']}"]
    return "\n".join(lines)


def read_summary(out: str | Path) -> dict:
    return json.loads((Path(out) / "summary.json").read_text())
