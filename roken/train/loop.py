"""The pretraining loop, without Ray: AdamW, warm-up + cosine / constant schedule, gradient clipping, EMA,
bf16 autocast on CUDA, optional torch.compile, validation, checkpoints, resume.

    run = Pretraining(spec, data="data/train", out="runs/x")     # in-process (pipelines/pretrain.py --workers 0)
    run.fit()

The same `fit` runs in every Ray Train worker (pipelines/pretrain.py); a `Backend` says what differs there:
rank and world size, the DDP wrapper, where checkpoints go and where a resumed run's state comes from.
"""
from __future__ import annotations

import copy
import json
import math
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from ..data.build import changed_keys, code_version
from ..devices import pick_device
from ..data.loader import to_device
from ..data.store import atomic_write_json
from ..data.samples import SampleConfig
from ..model.diffusion import DiffusionConfig, NoiseSchedule, check as check_diffusion
from ..model.dit import ModelConfig, RokenDiT, check as check_model
from ..model.losses import LossConfig, check as check_loss, pretraining_loss
from ..plan.rollout import PlanConfig
from ..rl.selfcost import SelfCost, SelfCostConfig, active
from ..world.maps import MapConfig
from ..world.tasks import TaskConfig
from . import checkpoint as ckpt
from .data import SampleStream, fingerprint, load_banks, make_loader
from .logger import RunLogger, duration
from .closed_loop import format_closed_loop
from .validation import Validator, format_validation


class Diverged(ValueError):
    """A non-finite loss or gradient: the run stops, keeping its last good checkpoint."""


@dataclass
class TrainConfig:
    steps: int = 60_000  # optimizer steps (paper: 200 epochs of its dataset at batch 128)
    batch_size: int = 128  # global batch, split over the workers (paper)
    lr: float = 5e-4  # AdamW (paper)
    weight_decay: float = 0.01  # AdamW's usual default; the paper names AdamW without a value
    warmup_steps: int = 1000  # linear warm-up from 0
    schedule: str = "cosine"  # "cosine" (to min_lr_ratio * lr at `steps`) or "constant" after warm-up
    min_lr_ratio: float = 0.1
    grad_clip: float = 1.0  # max global gradient norm (0 = off)
    ema_decay: float = 0.999  # EMA of the weights, the weights planners load; warmed up as min(d, (1+s)/(10+s))
    log_every: int = 50
    eval_every: int = 1000  # validation (loss terms + sampled-chunk metrics on held-out prompts); 0 = off
    checkpoint_every: int = 1000
    keep_checkpoints: int = 3  # the newest ones (and the best by validation L_traj) are kept
    seed: int = 0
    val_fraction: float = 0.05  # maps held out of --data when no --val-data is given
    val_prompts: int = 64
    ddim_steps: int = 10  # sampler steps of the validation chunks
    noise_draws: int = 1  # K (Mini-Diffuser): (k, eps) draws per sample against one map encoding (losses.py)
    closed_loop_every: int = 1000  # closed-loop validation on `val` tasks every this many steps and at the end; 0 = off
    closed_loop_tasks: int = 32  # fixed held-out tasks of the `val` map split (roken/train/closed_loop.py)
    closed_loop_robots: int = 4
    time_budget_s: float = 0.0  # stop (with a checkpoint) after this much training time, validation excluded; 0 = off
    loader_workers: int = 2  # DataLoader processes per training worker
    compile: bool = False  # torch.compile the model (GPU; minutes of compile time)
    precision: str = "auto"  # "auto" = bf16 autocast on CUDA, fp32 on CPU; or "fp32" / "bf16"
    device: str = "auto"  # "auto" = CUDA when available


def check(cfg: TrainConfig) -> None:
    if cfg.steps < 1 or cfg.batch_size < 1:
        raise ValueError(f"train.steps and train.batch_size must be >= 1 (got {cfg.steps}, {cfg.batch_size})")
    if cfg.schedule not in ("cosine", "constant"):
        raise ValueError(f"train.schedule must be 'cosine' or 'constant', got {cfg.schedule!r}")
    if cfg.precision not in ("auto", "fp32", "bf16"):
        raise ValueError(f"train.precision must be 'auto', 'fp32' or 'bf16', got {cfg.precision!r}")
    if not 0 <= cfg.ema_decay < 1 or cfg.lr <= 0 or not 0 <= cfg.val_fraction < 1:
        raise ValueError("train.ema_decay in [0, 1), train.lr > 0, train.val_fraction in [0, 1)")
    for k in ("log_every", "checkpoint_every", "noise_draws"):
        if getattr(cfg, k) < 1:
            raise ValueError(f"train.{k} must be >= 1, got {getattr(cfg, k)}")
    if cfg.closed_loop_every < 0 or cfg.closed_loop_tasks < 1 or cfg.closed_loop_robots < 1:
        raise ValueError("train.closed_loop_every must be >= 0 (0 = off), train.closed_loop_tasks and "
                         "train.closed_loop_robots >= 1")


@dataclass
class PretrainSpec:
    """The sections pretraining reads (and writes into every checkpoint's config.json)."""
    train: TrainConfig = field(default_factory=TrainConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    samples: SampleConfig = field(default_factory=SampleConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    plan: PlanConfig = field(default_factory=PlanConfig)  # the closed-loop validation's planner settings
    map: MapConfig = field(default_factory=MapConfig)  # the `val` maps of the closed-loop validation
    selfcost: SelfCostConfig = field(default_factory=SelfCostConfig)  # the cost of the model's own samples

    @classmethod
    def of(cls, cfg) -> "PretrainSpec":
        return cls(cfg.train, cfg.model, cfg.diffusion, cfg.samples, cfg.loss, cfg.task, cfg.plan, cfg.map,
                   cfg.selfcost)


def lr_factor(step: int, cfg: TrainConfig) -> float:
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    if cfg.schedule == "constant":
        return 1.0
    t = min(1.0, (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps))
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * t))


class LocalBackend:
    """In-process: one worker, checkpoints written straight into the run folder."""
    rank, world = 0, 1

    def __init__(self, run_dir: str | Path, device: torch.device):
        self.run_dir, self.device = Path(run_dir), device

    def prepare(self, model: torch.nn.Module) -> torch.nn.Module:
        return model

    def resume_from(self) -> Path | None:
        ckpt.remove_temporaries(self.run_dir)
        found = ckpt.list_checkpoints(self.run_dir)
        return found[-1] if found else None

    def report(self, step: int, metrics: dict, write=None, keep: int = 3) -> None:
        """`write(directory)` fills a checkpoint; it goes to run_dir/checkpoint-{step} atomically."""
        if write is not None:
            ckpt.write_atomic(self.run_dir, step, write)
            ckpt.prune(self.run_dir, keep)


def check_sections(cfg) -> None:
    """Every section pretraining reads (a config or a PretrainSpec), alone and against each other: what a run
    checks before it writes anything, and what `ablate.py` checks for every variant before the first trains."""
    check(cfg.train)
    check_loss(cfg.loss)
    check_model(cfg.model)
    check_diffusion(cfg.diffusion)
    ckpt.cross_check(cfg.model, cfg.samples, cfg.task.max_step, "config")


class Pretraining:
    def __init__(self, spec: PretrainSpec, data: str | list[str], out: str | Path, val_data: str | None = None,
                 backend=None, log_stream=None, data_shares: list[float] | None = None, init: str | None = None):
        """`data`: one dataset, or several mixed by `data_shares` (DAgger). `init`: a checkpoint a new run starts
        from (weights, EMA and, where it has one, the optimizer state; its step and schedule are not taken)."""
        check_sections(spec)
        self.spec, self.data, self.data_shares, self.out = spec, data, data_shares, Path(out)
        t = spec.train
        self.device = getattr(backend, "device", None) or pick_device(t.device)
        self.backend = backend or LocalBackend(self.out, self.device)
        self.rank, self.world = self.backend.rank, self.backend.world
        if t.batch_size % self.world:
            raise ValueError(f"train.batch_size={t.batch_size} is not divisible by {self.world} workers")
        self.main = self.rank == 0
        if self.device.type == "cpu":
            torch.set_flush_denormal(True)  # zero-initialised AdaLN drives Adam states into denormals: 4x slower
        self.train_bank, self.val_bank, self.source_weights = load_banks(
            data, spec.samples.canvas, val_data, t.val_fraction, t.seed, data_shares)
        self.init = init
        self.log_stream = log_stream
        self.amp = (t.precision == "bf16") or (t.precision == "auto" and self.device.type == "cuda")
        self.selfcost = None  # the constraint cost of the model's own samples, beside the denoising loss
        if active(spec.selfcost):
            self.selfcost = SelfCost(spec.selfcost, spec.samples, spec.plan, spec.task, self.rank)

    # -- model, optimizer, state -------------------------------------------------------------------------
    def _build(self):
        t = self.spec.train
        torch.manual_seed(t.seed)  # identical initial weights on every rank (DDP also broadcasts them)
        self.model = RokenDiT(self.spec.model).to(self.device)
        self.ema = copy.deepcopy(self.model).requires_grad_(False).eval()
        decay, no_decay = [], []
        for name, p in self.model.named_parameters():
            (decay if p.ndim >= 2 and "phi_mg" not in name and "phi_mtau" not in name else no_decay).append(p)
        self.opt = torch.optim.AdamW([{"params": decay, "weight_decay": t.weight_decay},
                                      {"params": no_decay, "weight_decay": 0.0}], lr=t.lr, betas=(0.9, 0.999),
                                     fused=self.device.type == "cuda")
        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, lambda s: lr_factor(s, t))
        self.noise = NoiseSchedule(self.spec.diffusion, self.device)
        self.net = self.backend.prepare(self.model)
        if t.compile:
            self.net = torch.compile(self.net)
        self.step = 0
        self.ema_offset = 0  # steps the EMA had averaged before this run (a run started from `init`)
        self.train_seconds = 0.0  # optimizer time so far (validation excluded): the time budget's clock

    def state(self) -> dict:
        return {"model": self.model.state_dict(), "ema": self.ema.state_dict(), "optimizer": self.opt.state_dict(),
                "scheduler": self.sched.state_dict(), "step": self.step, "ema_offset": self.ema_offset, "train_seconds": self.train_seconds,
                "rng": ckpt.rng_state()}

    def load_state(self, s: dict) -> None:
        self.model.load_state_dict(s["model"])
        self.ema.load_state_dict(s["ema"])
        self.opt.load_state_dict(s["optimizer"])
        self.sched.load_state_dict(s["scheduler"])
        self.step = int(s["step"])
        self.ema_offset = int(s.get("ema_offset", 0))
        self.train_seconds = float(s.get("train_seconds", 0.0))
        ckpt.set_rng_state(s["rng"])

    def _load_init(self, path: str) -> None:
        """Start from another run's checkpoint (DAgger's rounds): its weights and EMA, and its optimizer moments
        when it has a train_state.pt (a fresh Adam at full lr would shake a trained model). A checkpoint without
        the last-move input may start a run with `model.prev_move`, one without the team-mates' offsets with
        `model.neighbours` (a new input starts at 0, its moments fresh)."""
        loaded = ckpt.load(path, "cpu")
        self.ema_offset = int(loaded.config.get("step", 0)) + int(loaded.config.get("ema_offset", 0))
        old, own = asdict(loaded.model_cfg), asdict(self.spec.model)
        # zero-initialised inputs a run may add to a checkpoint without them: (config key, its value when off,
        # the parameters it brings)
        inputs = (("prev_move", False, "phi_prev."), ("neighbours", 0, "phi_nbr."))
        added = [(key, off, prefix) for key, off, prefix in inputs if old.get(key, off) == off and own[key] != off]
        adds_inputs = bool(added) and {**old, **{key: own[key] for key, _, _ in added}} == own
        if old != own and not adds_inputs:
            raise ckpt.CheckpointError(f"{loaded.path}: its model section differs from this run's "
                                       f"({', '.join(changed_keys(old, own, 'model.')[:4])}); "
                                       f"start from a checkpoint of the same model config")
        ckpt.same_diffusion(loaded.path, self.spec.diffusion)
        if (loaded.path / ckpt.STATE).is_file():
            s = ckpt.load_train_state(loaded.path)
            model, ema, optimizer = s["model"], s["ema"], s["optimizer"]
        else:  # inference weights only (an exported model): the EMA weights start both copies
            model = ema = loaded.model.state_dict()
            optimizer = None
        if adds_inputs:
            missing = self.model.load_state_dict(model, strict=False).missing_keys
            self.ema.load_state_dict(ema, strict=False)
            prefixes = tuple(prefix for _, _, prefix in added)
            if any(not k.startswith(prefixes) for k in missing):
                raise ckpt.CheckpointError(f"{loaded.path}: weights missing {missing[:4]}")
            optimizer = optimizer and ckpt.moments_without(optimizer, self.model, self.opt, prefixes)
        else:
            self.model.load_state_dict(model)
            self.ema.load_state_dict(ema)
        if optimizer is not None:
            self.opt.load_state_dict(optimizer)

    def config_dict(self, validation: dict | None = None) -> dict:
        return {"model": asdict(self.spec.model), "diffusion": asdict(self.spec.diffusion),
                "samples": asdict(self.spec.samples), "loss": asdict(self.spec.loss), "train": asdict(self.spec.train),
                "selfcost": asdict(self.spec.selfcost),
                "task": asdict(self.spec.task), "dataset": fingerprint(self.data), "data_shares": self.data_shares,
                "code_version": code_version(),
                "step": self.step, "ema_offset": self.ema_offset, "init": self.init, "world_size": self.world, "validation": validation or {},
                "kind": "roken-pretraining"}

    # -- one optimizer step --------------------------------------------------------------------------------
    def train_step(self, batch: dict) -> dict[str, torch.Tensor]:
        t = self.spec.train
        with torch.autocast(self.device.type, dtype=torch.bfloat16) if self.amp else nullcontext():
            loss, logs = pretraining_loss(self.net, self.noise, batch, self.spec.loss, self.spec.samples,
                                          step=self.step, draws=t.noise_draws)
            if self.selfcost is not None:
                # the bare module (not the DDP wrapper): its gradient joins the same backward, whose hooks average it
                extra, extra_logs = self.selfcost(self.model, self.noise, self.step)
                loss, logs = loss + extra, logs | extra_logs
                logs["losses/total"] = loss.detach()
        if not torch.isfinite(loss):  # stop before a non-finite backward (lr 1e12 segfaulted there)
            bad = [k[7:] for k, v in logs.items() if k != "losses/total" and not torch.isfinite(v)]
            raise Diverged(f"training diverged at step {self.step}: the loss is {float(loss.detach())} (non-finite terms: "
                           f"{', '.join(bad) or 'the weighted sum'}); the last good checkpoint is kept. Lower "
                           f"train.lr (now {t.lr:g}) or keep train.warmup_steps > 0")
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), t.grad_clip if t.grad_clip > 0 else float("inf"))
        if not torch.isfinite(norm):
            raise Diverged(f"training diverged at step {self.step}: the gradient norm is {float(norm)} (loss "
                           f"{float(loss):.4g}); the last good checkpoint is kept. Lower train.lr (now {t.lr:g})")
        self.opt.step()
        self.sched.step()
        self._ema_update()
        self.step += 1
        logs["charts/grad_norm"] = norm.detach()
        return logs

    @torch.no_grad()
    def _ema_update(self) -> None:
        s = self.step + self.ema_offset  # a run started from a trained model keeps its EMA horizon
        d = min(self.spec.train.ema_decay, (1 + s) / (10 + s))
        ema, cur = list(self.ema.parameters()), list(self.model.parameters())
        torch._foreach_lerp_(ema, cur, 1 - d)

    # -- the run -----------------------------------------------------------------------------------------
    def fit(self) -> dict:
        t = self.spec.train
        self._build()
        resume = self.backend.resume_from()
        if resume is not None:
            self.load_state(ckpt.load_train_state(resume))
        elif self.init is not None:
            self._load_init(self.init)
        done = self.out / "summary.json"
        if resume is not None and (self.step >= t.steps or self._out_of_time()) and done.is_file():
            return json.loads(done.read_text())  # a finished run: its summary, nothing rewritten
        log = RunLogger(self.out, self.main, self.step, self.log_stream)
        start = self.step
        stream = SampleStream(self.train_bank, self.spec.samples, t.seed, self.source_weights)
        validator = None
        if self.main and self.val_bank is not None and t.eval_every > 0:
            validator = Validator(self.val_bank, self.spec.samples, self.spec.loss, self.noise, t.val_prompts,
                                  t.ddim_steps, self.spec.task.d_obs_min, self.spec.task.d_coll_min,
                                  self.spec.task.comm_radius, seed=t.seed + 1234,
                                  executed=self.spec.plan.replan_every)
        closed = None
        if self.main and t.closed_loop_every > 0:
            from .closed_loop import ClosedLoopValidator  # plan imports train: imported here, not at the top
            closed = ClosedLoopValidator(t.closed_loop_tasks, t.closed_loop_robots, self.spec.task, self.spec.plan,
                                         self.spec.map, seed=t.seed)
        local = t.batch_size // self.world
        log.print(f"[pretrain] {self.spec.model.width}w x {self.spec.model.depth} layers, "
                  f"{self.model.num_params() / 1e6:.2f}M params on {self.device}{' bf16' if self.amp else ''}; "
                  f"{len(self.train_bank)} training episodes, "
                  f"{len(self.val_bank) if self.val_bank is not None else 0} held out; global batch {t.batch_size} "
                  f"= {local} x {self.world} worker(s); "
                  + (f"resuming at step {start} from {resume}" if resume else f"steps 0..{t.steps}"))
        loader = make_loader(stream, start, t.steps, t.batch_size, self.rank, self.world, t.loader_workers,
                             pin=self.device.type == "cuda")
        last_val: dict = {}
        metrics: dict = {}
        sums: dict[str, torch.Tensor] = {}
        n_sums, wait, t_win, t0 = 0, 0.0, time.perf_counter(), time.perf_counter()
        it = iter(loader)
        out_of_time = self._out_of_time()
        while self.step < t.steps and not out_of_time:
            w0 = time.perf_counter()
            batch = to_device(next(it), self.device)
            wait += time.perf_counter() - w0
            logs = self.train_step(batch)
            for k, v in logs.items():  # tensors: summing them does not wait for the device every step
                sums[k] = sums.get(k, 0.0) + v
            n_sums += 1
            self.train_seconds += time.perf_counter() - w0
            metrics = {}
            if self.step % t.log_every == 0 or self.step == t.steps:
                out_of_time = self._out_of_time()
            last = self.step == t.steps or out_of_time
            if self.step % t.log_every == 0 or last:
                now = time.perf_counter()
                rate = n_sums * t.batch_size / (now - t_win)
                metrics = {k: float(v) / n_sums for k, v in sums.items()} | {
                    "charts/lr": self.sched.get_last_lr()[0], "charts/samples_per_s": rate,
                    "charts/data_wait_frac": wait / (now - t_win), "charts/epoch": self.step * t.batch_size /
                    len(self.train_bank), "charts/draws_per_s": rate * t.noise_draws,
                    "time/train_s": self.train_seconds}
                eta = (t.steps - self.step) * t.batch_size / rate
                if t.time_budget_s > 0:  # a time-budgeted run ends when its training time is spent
                    eta = min(eta, max(t.time_budget_s - self.train_seconds, 0.0))
                done = self.step / t.steps if t.time_budget_s <= 0 else max(self.step / t.steps,
                                                                            self.train_seconds / t.time_budget_s)
                log.print(f"[pretrain] step {self.step}/{t.steps} ({100 * done:.1f}%) "
                          f"loss {metrics['losses/total']:.4f} traj {metrics['losses/traj']:.4f}"
                          + "".join(f" {k.split('/')[-1]} {metrics[k]:.4f}"
                                    for k in ("losses/wp", "losses/occ", "losses/sdf", "losses/sep", "losses/selfcost",
                                              "losses/distil", "selfcost/violating", "selfcost/target_violating")
                                    if k in metrics)
                          + f" | {rate:.0f} samples/s, data wait {100 * metrics['charts/data_wait_frac']:.0f}%, "
                          f"lr {metrics['charts/lr']:.2e}, ETA {duration(eta)}")
                sums, n_sums, wait, t_win = {}, 0, 0.0, now
            if validator is not None and (self.step % t.eval_every == 0 or last):
                v0 = time.perf_counter()
                last_val = validator.evaluate(self.ema, self.device, _autocast(self.device, self.amp))
                metrics |= last_val
                t_win += time.perf_counter() - v0  # validation time does not count against the training rate
                log.print(f"[pretrain] validation at step {self.step}: held-out loss "
                          f"{last_val['val/losses/total']:.4f} (traj {last_val['val/losses/traj']:.4f}), "
                          f"first-move cosine leader {last_val['val/first_move_cos_leader']:.3f} follower "
                          f"{last_val['val/first_move_cos_follower']:.3f}, executed L2 "
                          f"{last_val['val/l2_executed_m']:.3f} m\n" + format_validation(last_val))
            if closed is not None and (self.step % t.closed_loop_every == 0 or last):
                v0 = time.perf_counter()
                cl = closed.evaluate(self.ema, self.noise, self.spec.samples, self.device) | {
                    "closed_loop/step": float(self.step)}
                last_val = {k: v for k, v in last_val.items() if not k.startswith("closed_loop/")} | cl
                metrics |= cl
                t_win += time.perf_counter() - v0
                log.print(f"[pretrain] step {self.step}: " + format_closed_loop(cl)
                          + f" ({cl['time/closed_loop_s']:.0f} s, {int(cl['closed_loop/episodes'])} episodes)")
            if metrics:
                log.log(self.step, metrics)
            if self.step % t.checkpoint_every == 0 or last:  # every rank reports together
                writer = self._writer(last_val) if self.main else None
                self.backend.report(self.step, {"step": self.step} | _scalars(metrics), writer, t.keep_checkpoints)
        wall = time.perf_counter() - t0
        log.close()
        summary = {"steps": self.step, "resumed_from": start, "samples": (self.step - start) * t.batch_size,
                   "wall_s": wall, "train_s": self.train_seconds, "stopped_by_time_budget": bool(out_of_time),
                   "noise_draws": t.noise_draws, "workers": self.world, "global_batch": t.batch_size,
                   "final": {k: v for k, v in _scalars(metrics).items() if k.startswith("losses/")},
                   "validation": _scalars(last_val), "checkpoint": str(self.out / ckpt.checkpoint_name(self.step))}
        if self.main:
            atomic_write_json(summary, self.out / "summary.json")
        return summary

    def _out_of_time(self) -> bool:
        """train.time_budget_s spent? Every rank takes rank 0's answer, so DDP workers stop at the same step."""
        b = self.spec.train.time_budget_s
        flag = float(b > 0 and self.train_seconds >= b)
        if self.world > 1 and torch.distributed.is_available() and torch.distributed.is_initialized():
            x = torch.tensor([flag])
            torch.distributed.broadcast(x, 0)
            flag = float(x[0])
        return bool(flag)

    def _writer(self, validation: dict):
        config, state = self.config_dict(_scalars(validation)), self.state()
        weights = {k: v.detach().clone() for k, v in self.ema.state_dict().items()}

        def write(directory: Path) -> None:
            ckpt.write(directory, weights, config, state)
        return write


def _autocast(device: torch.device, amp: bool):
    return torch.autocast(device.type, dtype=torch.bfloat16) if amp else None


def _scalars(d: dict) -> dict:
    return {k: float(v) for k, v in d.items()}


def summary_table(summary: dict) -> str:
    rows = [("steps", f"{summary['resumed_from']} -> {summary['steps']}"), ("samples", f"{summary['samples']:,}"),
            ("wall time", duration(summary["wall_s"]))]
    rows += [(k, f"{v:.4f}") for k, v in sorted(summary["final"].items())]
    v = summary.get("validation") or {}
    rows += [(k, f"{v[k]:.4f}") for k in ("val/losses/total", "val/losses/traj", "val/first_move_cos_leader",
                                          "val/first_move_cos_follower", "val/l2_executed_m") if k in v]
    rows += [(k, f"{v[k]:.3f}") for k in ("closed_loop/success", "closed_loop/reach", "closed_loop/obstacle_collision",
                                          "closed_loop/inter_collision", "closed_loop/connectivity") if k in v]
    width = max(len(r[0]) for r in rows)
    out = "\n".join(f"{k:<{width}}  {val}" for k, val in rows)
    if v:
        out += "\nvalidation chunks (DDIM, held-out prompts):\n" + format_validation(v)
    return out + f"\ncheckpoint: {summary['checkpoint']}"
