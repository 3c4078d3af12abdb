"""DAgger rounds (Ross et al. 2011) with the Laplacian expert as the relabeller, resumable per round.

Round r, in RUN/round-rr/:
  rollouts/  the current model in closed loop on `dagger.episodes` new `train`-map tasks (the evaluation
             harness: Ray actors or in-process, episodes and metrics.json as any evaluation);
  data/      the expert's continuations from the visited states (roken.dagger.relabel), a dataset folder
             (maps/, episodes/relabel.parquet with `source` and `round`, manifest.json written last), and
             with `dagger.keep_success` the successful rollouts as executed (source "self");
  train/     a pretraining run on the expert dataset mixed with every round's relabelled episodes so far
             (`dagger.share` of the samples), started from the previous round's model (weights, EMA,
             optimizer), `dagger.steps_per_round` steps, closed-loop validation on the `val` tasks at its end;
  summary.json  the round's figures, written when the round is done (a re-run skips the round).
Every stage is deterministic (task seeds, expert, the step-indexed sample stream), so an interrupted round
resumed with the same command gives what an uninterrupted one gives.
"""
from __future__ import annotations

import copy
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

from ..data.build import changed_keys, code_version
from ..data.store import (SCHEMA_VERSION, atomic_write_json, atomic_write_table, episodes_table, maps_table,
                          read_json, read_run)
from ..eval.harness import EvalConfig, evaluate
from ..rl.selfcost import active
from ..train import checkpoint as ckpt
from .relabel import DaggerConfig, check, relabel

DATA_SHARD = "episodes/relabel.parquet"


def round_dir(out: str | Path, r: int) -> Path:
    return Path(out) / f"round-{r:02d}"


def run_config(cfg, checkpoint: str, data: str, val_data: str | None) -> dict:
    """What a DAgger run folder is made of; a re-run with other values is refused (rounds may be raised)."""
    sections = {k: json.loads(json.dumps(asdict(getattr(cfg, k)), default=str))
                for k in ("dagger", "model", "diffusion", "samples", "loss", "task", "expert", "plan", "selfcost")}
    sections["dagger"].pop("rounds")
    sections["train"] = {k: v for k, v in asdict(cfg.train).items()
                         if k not in ("steps", "log_every", "loader_workers", "device", "time_budget_s")}
    return {"checkpoint": str(Path(checkpoint).resolve()), "data": data, "val_data": val_data} | sections


def check_run(out: str | Path, cfg, checkpoint: str, data: str, val_data: str | None) -> None:
    path = Path(out) / "dagger.json"
    new = json.loads(json.dumps(run_config(cfg, checkpoint, data, val_data), default=str))
    if path.is_file():
        from ..config import Config  # (the root config imports this package)

        # options newer than the run folder: their defaults, so an older run resumes as it was made
        defaults = json.loads(json.dumps(run_config(Config(), checkpoint, data, val_data), default=str))
        old = read_json(path)
        old = {k: defaults[k] | old[k] if isinstance(defaults.get(k), dict) and isinstance(old.get(k), dict)
               else old.get(k, defaults.get(k)) for k in set(defaults) | set(old)}
        changed = changed_keys(old, new)
        if changed:
            raise ValueError(f"{out} holds a DAgger run made with other settings ({'; '.join(changed[:6])}); its "
                             f"rounds are kept. Use a new --out, or the old settings to resume it (--rounds may grow)")
    else:
        atomic_write_json(new, path)


def rollout_seed(dc: DaggerConfig, r: int) -> int:
    """The task seed of round r's rollouts: new tasks every round, or round 0's with `dagger.same_tasks`."""
    return 1000 * (dc.seed + 1) + (0 if dc.same_tasks else r)


def rollout(cfg, dc: DaggerConfig, model: str, r: int, out: Path, runner) -> dict:
    """The current model in closed loop on this round's `train` tasks (`dagger.planner`, plan section as
    configured)."""
    c = copy.deepcopy(cfg)
    c.eval = EvalConfig(planner=dc.planner, robots=[dc.robots], episodes=dc.episodes, maps="train",
                        num_maps=dc.num_maps, seed=rollout_seed(dc, r), unit_episodes=16)
    c.plan.checkpoint, c.plan.which = model, "latest"
    return evaluate(c, out, runner)


def relabel_round(cfg, dc: DaggerConfig, r: int, rollouts: Path, out: Path) -> dict:
    if (out / "manifest.json").is_file():
        return read_json(out / "manifest.json")["stats"]
    maps, episodes = read_run(rollouts)
    t0 = time.perf_counter()
    rows, stats = relabel(episodes, maps, r, dc, cfg.task, cfg.expert)
    stats["relabel_s"] = round(time.perf_counter() - t0, 2)
    used = sorted({row["map_id"] for row in rows})
    atomic_write_table(maps_table([maps[m] for m in used]), out / "maps" / "maps.parquet", "maps")
    atomic_write_table(episodes_table(rows), out / DATA_SHARD, "episodes", {"round": r, "source": "dagger"})
    manifest = {"kind": "roken-dataset", "schema_version": SCHEMA_VERSION, "status": "finished",
                "source": "dagger", "round": r, "episodes": len(rows), "maps": len(used),
                "shards": [{"episodes": DATA_SHARD, "rows": len(rows)}], "stats": stats,
                "config": {"dataset": {"maps": "train"}, "dagger": asdict(dc), "task": asdict(cfg.task),
                           "expert": asdict(cfg.expert)}, "code_version": code_version(), "command": sys.argv}
    atomic_write_json(manifest, out / "manifest.json")  # last: its presence marks the stage done
    return stats


def round_config(cfg, model: str, out: Path | None = None, r: int = 0):
    """The root config of a round's training: `dagger.steps_per_round` steps, validated (open and closed loop)
    at the end, no time budget, and no warm-up when the optimizer moments come with the model. With the
    `selfcost` term on and no `selfcost.states` of its own, its states are the rollouts of every round so far
    (the learner's own states, refreshed each round: the term is on-policy as the relabels are)."""
    c = copy.deepcopy(cfg)
    if active(c.selfcost) and not c.selfcost.states.strip() and out is not None:
        c.selfcost.states = ",".join(str(round_dir(out, k) / "rollouts") for k in range(r + 1))
    t, n = c.train, cfg.dagger.steps_per_round
    t.steps, t.closed_loop_every, t.eval_every, t.time_budget_s = n, n, n, 0.0
    t.checkpoint_every = min(t.checkpoint_every, n)
    if (Path(model) / ckpt.STATE).is_file():
        t.warmup_steps = 0
    return c


def mix(data: str, out: Path, r: int, share: float) -> tuple[list[str], list[float]]:
    """The expert dataset and every round's relabelled data so far, with their shares of the samples (the
    relabelled share split over the rounds in proportion to their successful episodes)."""
    rounds = [round_dir(out, k) / "data" for k in range(r + 1)]
    stats = [read_json(d / "manifest.json")["stats"] for d in rounds]
    kept = [st["states"] * st["expert_success"] + st.get("self", 0) for st in stats]
    total = sum(kept)
    if total <= 0:
        return [data], [1.0]
    used = [(str(d), share * k / total) for d, k in zip(rounds, kept) if k > 0]
    return [data] + [d for d, _ in used], [1.0 - share] + [s for _, s in used]


def start_figures(cfg, first: Path, out: Path) -> dict:
    """The starting model's closed-loop figures on the same `val` tasks every round's training reports on."""
    path = out / "start.json"
    if path.is_file():
        return read_json(path)
    from ..train.closed_loop import ClosedLoopValidator

    t = cfg.train
    loaded = ckpt.load(first, "cpu", task_max_step=cfg.task.max_step)
    m = ClosedLoopValidator(t.closed_loop_tasks, t.closed_loop_robots, cfg.task, cfg.plan, cfg.map,
                            seed=t.seed).evaluate(loaded.model, loaded.schedule, loaded.samples)
    atomic_write_json(m, path)
    return m


def run_dagger(cfg, checkpoint: str, data: str, out: str | Path, make_runner, train, val_data: str | None = None,
               log=print) -> dict:
    """Run (or finish) `dagger.rounds` rounds into `out`; returns {"rounds": [per-round summaries]}.

    make_runner(): a fresh unit runner for the rollouts (the harness shuts it down after each);
    train(cfg, datasets, shares, run_dir, val_data, init) -> the pretraining summary of one round (cfg: the
    round's root config, roken.dagger.rounds.round_config)."""
    dc: DaggerConfig = cfg.dagger
    check(dc)
    out = Path(out)
    first = ckpt.find(checkpoint).resolve()  # a bad checkpoint fails here, before anything is written (absolute: Ray workers run elsewhere)
    check_run(out, cfg, checkpoint, data, val_data)
    start = start_figures(cfg, first, out)
    summaries, model = [], str(first)
    for r in range(dc.rounds):
        d = round_dir(out, r)
        if (d / "summary.json").is_file():
            s = read_json(d / "summary.json")
            log(f"[dagger] round {r}: done earlier ({s['states']} states relabelled, closed-loop success "
                f"{s['closed_loop/success']:.3f})")
            summaries.append(s)
            model = s["checkpoint"]
            continue
        t0 = time.perf_counter()
        log(f"[dagger] round {r}/{dc.rounds}: rolling out {Path(model).parent.name}/{Path(model).name} on "
            f"{dc.episodes} train tasks")
        ro = rollout(cfg, dc, model, r, d / "rollouts", make_runner())
        stats = relabel_round(cfg, dc, r, d / "rollouts", d / "data")
        log(f"[dagger] round {r}: rollout success {ro['full_success']:.3f} (reach {ro['reach']:.3f}); relabelled "
            f"{stats['states']} states (refused {stats['refused']}), expert success from them "
            f"{stats['expert_success']:.3f}" + (f"; {stats['self']} successful rollouts kept as executed"
                                           if stats.get("self") else ""))
        datasets, shares = mix(data, out, r, dc.share)
        t_train = train(round_config(cfg, model, out, r), datasets, shares, str(d / "train"), val_data, model)
        val = t_train.get("validation", {})
        s = {"round": r, "rollouts": stats["rollouts"], "rollout_success": ro["full_success"],
             "rollout_reach": ro["reach"], "states": stats["states"], "refused": stats["refused"],
             "expert_success": stats["expert_success"], "datasets": datasets, "shares": shares,
             "train_steps": t_train["steps"], "train_s": t_train["train_s"]} | {
            k: val.get(k) for k in ("closed_loop/success", "closed_loop/reach", "closed_loop/obstacle_collision",
                                    "val/first_move_cos_follower", "val/l2_executed_m")} | {
            "checkpoint": t_train["checkpoint"], "seconds": round(time.perf_counter() - t0, 1)}
        atomic_write_json(s, d / "summary.json")
        summaries.append(s)
        model = s["checkpoint"]
        log(f"[dagger] round {r}: closed-loop success on val tasks {s['closed_loop/success']:.3f} (reach "
            f"{s['closed_loop/reach']:.3f}), {s['seconds']:.0f} s")
    result = {"start": {k: start.get(k) for k in ("closed_loop/success", "closed_loop/reach")},
              "start_checkpoint": str(first), "rounds": summaries, "checkpoint": model}
    atomic_write_json(result, out / "summary.json")
    return result


def summary_table(result: dict) -> str:
    head = "| round | rollouts | rollout success | states relabelled | expert success from them | closed-loop success (val) | reach (val) | follower move-0 cos |"
    lines = [head, "|" + " --- |" * 8]
    st = result.get("start", {})
    lines.append(f"| start | | | | | {_f(st.get('closed_loop/success'))} | {_f(st.get('closed_loop/reach'))} | |")
    for s in result["rounds"]:
        lines.append(f"| {s['round']} | {s['rollouts']} | {_f(s['rollout_success'])} | {s['states']} | "
                     f"{_f(s['expert_success'])} | {_f(s['closed_loop/success'])} | {_f(s['closed_loop/reach'])} | "
                     f"{_f(s['val/first_move_cos_follower'])} |")
    return "\n".join(lines)


def _f(x) -> str:
    return "" if x is None else f"{x:.3f}"
