"""Checkpoints (ARCHITECTURE.md): one directory each, written atomically, loadable by any planner.

    model.safetensors   the weights planners use (EMA for pretraining; fp16 allowed for shipping)
    config.json         model, diffusion, samples, loss, the training section, task constants, dataset
                        fingerprint, code version, step, validation metrics
    train_state.pt      optional: weights, optimizer, schedule, EMA, step, RNG states (torch.load weights_only)

A run folder holds checkpoints as sub-directories named `checkpoint-{step:07d}`; anything that takes a
checkpoint also takes a run folder and picks its latest (or best) one.
"""
from __future__ import annotations

import json
import math
import os
import random
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from ..configtools import ConfigError, from_dict
from ..data.samples import SampleConfig
from ..model.diffusion import DiffusionConfig, NoiseSchedule
from ..model.dit import ModelConfig, RokenDiT
from ..model.losses import LossConfig

WEIGHTS, CONFIG, STATE = "model.safetensors", "config.json", "train_state.pt"
PREFIX = "checkpoint-"


class CheckpointError(ValueError):
    """A checkpoint that cannot be used as asked, with the file and the keys at fault."""


def checkpoint_name(step: int) -> str:
    return f"{PREFIX}{step:07d}"


def write(directory: str | Path, weights: dict[str, torch.Tensor], config: dict, train_state: dict | None = None,
          half: bool = False) -> Path:
    """Write the checkpoint files into `directory` (created; it should be a fresh temporary)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    tensors = {k: (v.detach().to("cpu", torch.float16 if half and v.is_floating_point() else v.dtype)).contiguous()
               for k, v in weights.items()}
    save_file(tensors, str(d / WEIGHTS), metadata={"format": "pt", "step": str(config.get("step", ""))})
    (d / CONFIG).write_text(json.dumps(config, indent=1, sort_keys=True, default=_json_default) + "\n")
    if train_state is not None:
        torch.save(train_state, d / STATE)
    return d


def _json_default(o):
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if hasattr(o, "item"):
        return o.item()
    return str(o)


def write_atomic(run_dir: str | Path, step: int, fill) -> Path:
    """run_dir/checkpoint-{step}, filled by `fill(directory)` in a hidden temporary renamed into place: a reader
    never sees a half-written checkpoint, and a checkpoint of the same step already there is kept."""
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    final = run / checkpoint_name(step)
    if final.exists():
        return final
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{final.name}-", dir=run))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; a checkpoint is an output like any other (the umask's)
    try:
        fill(tmp)
        os.rename(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def save_atomic(run_dir: str | Path, step: int, weights: dict, config: dict, train_state: dict | None = None,
                half: bool = False) -> Path:
    """Write a checkpoint of these weights and config into run_dir/checkpoint-{step} (see write_atomic)."""
    return write_atomic(run_dir, step, lambda d: write(d, weights, config, train_state, half))


def remove_temporaries(run_dir: str | Path) -> None:
    for p in Path(run_dir).glob(".tmp-" + PREFIX + "*"):
        shutil.rmtree(p, ignore_errors=True)


def list_checkpoints(run_dir: str | Path) -> list[Path]:
    """Complete checkpoints of a run folder (any sub-directory with config.json and weights), by step."""
    run = Path(run_dir)
    found = [p for p in run.iterdir() if p.is_dir() and not p.name.startswith(".")
             and (p / CONFIG).is_file() and (p / WEIGHTS).is_file()] if run.is_dir() else []
    return sorted(found, key=lambda p: (_read_config(p).get("step", -1), p.name))


def prune(run_dir: str | Path, keep: int) -> None:
    """Keep the newest `keep` checkpoints of a run folder, and its best (`find(..., "best")`)."""
    ckpts = list_checkpoints(run_dir)
    if keep <= 0 or len(ckpts) <= keep:
        return
    protected = set(ckpts[-keep:]) | {find(run_dir, "best")}
    for p in ckpts:
        if p not in protected:
            shutil.rmtree(p, ignore_errors=True)


def best_key(validation: dict, step: int | None = None) -> tuple | None:
    """What "best" ranks by, higher first: closed-loop success, ties broken by reach (roken/train/closed_loop.py),
    then the checkpoint the validation was measured on (later checkpoints carry the last figures until the next
    validation); a run without closed-loop validation falls back to the lowest held-out L_traj."""
    if validation.get("closed_loop/success") is not None:
        fresh = float(step is not None and validation.get("closed_loop/step") == step)
        return (1, float(validation["closed_loop/success"]), float(validation.get("closed_loop/reach") or 0.0), fresh)
    if validation.get("val/losses/traj") is not None:
        return (0, -float(validation["val/losses/traj"]), 0.0, 0.0)
    return None


def find(path: str | Path, which: str = "latest") -> Path:
    """A checkpoint directory, or a run folder's latest / best (`best_key`; the later of equals) one."""
    p = Path(path)
    if (p / CONFIG).is_file() or (p / WEIGHTS).is_file():
        return p
    if not p.exists():
        raise CheckpointError(f"{p}: no such checkpoint or run folder")
    ckpts = list_checkpoints(p)
    if not ckpts:
        raise CheckpointError(f"{p}: no checkpoint in this folder (a checkpoint directory holds {WEIGHTS} and "
                              f"{CONFIG}); train one with pipelines/pretrain.py --out {p}")
    if which == "latest":
        return ckpts[-1]
    if which != "best":
        raise ValueError(f"which must be 'latest' or 'best', got {which!r}")
    scored = [(key, i, c) for i, c in enumerate(ckpts)
              if (key := best_key((cfg := _read_config(c)).get("validation", {}), cfg.get("step")))]
    return max(scored)[2] if scored else ckpts[-1]


def _read_config(d: Path) -> dict:
    try:
        return json.loads((d / CONFIG).read_text())
    except (OSError, ValueError):
        return {}


def read_config(ckpt: str | Path) -> dict:
    d = Path(ckpt)
    try:
        return json.loads((d / CONFIG).read_text())
    except FileNotFoundError:
        raise CheckpointError(f"{d / CONFIG}: missing; a checkpoint directory holds {WEIGHTS} and {CONFIG}") from None
    except ValueError as e:
        raise CheckpointError(f"{d / CONFIG}: not valid JSON ({e}); the checkpoint is corrupt") from None


def cross_check(model: ModelConfig, samples: SampleConfig, task_max_step: float | None = None,
                source: str = "config") -> None:
    """The fields that several sections share must agree, or the model is fed inputs it was not trained on."""
    pairs = [("samples.horizon", samples.horizon, "model.horizon", model.horizon),
             ("samples.num_waypoints", samples.num_waypoints, "model.num_waypoints", model.num_waypoints),
             ("samples.patch", samples.patch, "model.occ_patch", model.occ_patch),
             ("samples.canvas", samples.canvas, "model.canvas", model.canvas)]
    if task_max_step is not None:
        pairs.append(("samples.max_step", samples.max_step, "task.max_step", task_max_step))
    bad = [f"{a}={va} vs {b}={vb}" for a, va, b, vb in pairs if va != vb]
    if model.canvas % model.map_patch or model.map_patch % 2:
        bad.append(f"model.canvas={model.canvas} must be a multiple of the even model.map_patch={model.map_patch}")
    if bad:
        raise CheckpointError(f"{source}: inconsistent settings: {'; '.join(bad)}")


def same_diffusion(path: str | Path, own: DiffusionConfig) -> None:
    """A run starting from the checkpoint at `path` (`--init`) must read its weights' output as they were trained:
    the diffusion section (diffusion.prediction, the schedule) must be the run's; only the clip may differ."""
    d = find(path)
    try:
        theirs = from_dict(DiffusionConfig, read_config(d).get("diffusion", {}), "diffusion.")
    except ConfigError as e:
        raise CheckpointError(f"{d / CONFIG}: {e} (written by another roken version?)") from None
    old, new = ({k: v for k, v in asdict(c).items() if k != "clip_sample"} for c in (theirs, own))
    if old != new:
        bad = [k for k in old if old[k] != new[k]]
        raise CheckpointError(f"{d}: its diffusion section differs from this run's ("
                              + ", ".join(f"diffusion.{k}: {old[k]} -> {new[k]}" for k in bad) + "); run with "
                              + " ".join(f"--set diffusion.{k}={old[k]}" for k in bad))


@dataclass
class Loaded:
    """A ready model (EMA weights, eval mode) with the sections it must be used with."""
    model: RokenDiT
    schedule: NoiseSchedule
    model_cfg: ModelConfig
    diffusion: DiffusionConfig
    samples: SampleConfig
    loss: LossConfig
    config: dict
    path: Path


def load(path: str | Path, device: str | torch.device = "cpu", which: str = "latest",
         task_max_step: float | None = None, dtype: torch.dtype = torch.float32) -> Loaded:
    """Load a checkpoint directory, or a run folder's latest / best checkpoint, as a ready model."""
    d = find(path, which)
    cfg = read_config(d)
    try:
        model_cfg = from_dict(ModelConfig, cfg["model"], "model.")
        diff = from_dict(DiffusionConfig, cfg["diffusion"], "diffusion.")
        samples = from_dict(SampleConfig, cfg["samples"], "samples.")
        loss = from_dict(LossConfig, cfg.get("loss", {}), "loss.")
    except KeyError as e:
        raise CheckpointError(f"{d / CONFIG}: section {e} missing; the checkpoint is incomplete") from None
    except ConfigError as e:
        raise CheckpointError(f"{d / CONFIG}: {e} (written by another roken version?)") from None
    cross_check(model_cfg, samples, task_max_step, str(d / CONFIG))
    model = RokenDiT(model_cfg)
    try:
        weights = load_file(str(d / WEIGHTS))
    except FileNotFoundError:
        raise CheckpointError(f"{d / WEIGHTS}: missing") from None
    except (SafetensorError, OSError, ValueError) as e:
        raise CheckpointError(f"{d / WEIGHTS}: not a readable safetensors file ({e}); the checkpoint is "
                              f"corrupt or was cut short") from None
    load_weights(model, weights, str(d / WEIGHTS))
    model = model.to(device=device, dtype=dtype).eval()
    return Loaded(model, NoiseSchedule(diff, device), model_cfg, diff, samples, loss, cfg, d)


def load_weights(model: torch.nn.Module, weights: dict[str, torch.Tensor], source: str) -> None:
    """Copy `weights` into `model`; missing, unexpected or mis-shaped keys are one error naming them."""
    own = model.state_dict()
    missing = sorted(set(own) - set(weights))
    extra = sorted(set(weights) - set(own))
    shape = sorted(k for k in set(own) & set(weights) if own[k].shape != weights[k].shape)
    if missing or extra or shape:
        parts = []
        if shape:
            parts.append("shape mismatch " + ", ".join(f"{k} {tuple(weights[k].shape)} vs model "
                                                       f"{tuple(own[k].shape)}" for k in shape[:4]))
        if missing:
            parts.append(f"missing {', '.join(missing[:4])}")
        if extra:
            parts.append(f"unexpected {', '.join(extra[:4])}")
        raise CheckpointError(f"{source}: weights do not fit the model in its config.json ({'; '.join(parts)}); "
                              f"a checkpoint of another model size or a different config.json")
    model.load_state_dict({k: v.to(own[k].dtype) for k, v in weights.items()})


def load_train_state(ckpt: str | Path) -> dict:
    p = Path(ckpt) / STATE
    try:
        return torch.load(p, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"{p}: missing; this checkpoint holds inference weights only and cannot resume "
                              f"training") from None
    except Exception as e:  # noqa: BLE001  (torch raises many types for a damaged pickle / zip)
        raise CheckpointError(f"{p}: cannot be read ({type(e).__name__}: {e}); the file is corrupt") from None


def moments_without(saved: dict, model: torch.nn.Module, opt: torch.optim.Optimizer, prefix: str | tuple) -> dict:
    """An optimizer state saved for `model` without its parameters named `prefix*` (a checkpoint from before
    they existed), re-indexed for `opt` over the whole model; the new parameters get fresh moments. torch keys an
    optimizer's state by position over its groups, so the positions are matched through parameter names."""
    name_of = {id(p): n for n, p in model.named_parameters()}
    names = [[name_of[id(p)] for p in g["params"]] for g in opt.param_groups]
    flat = [n for group in names for n in group]
    new_index = {n: i for i, n in enumerate(flat)}
    old_index = {n: i for i, n in enumerate(n for n in flat if not n.startswith(prefix))}
    groups = [{**g, "params": [new_index[n] for n in group]} for g, group in zip(saved["param_groups"], names)]
    state = {new_index[n]: saved["state"][i] for n, i in old_index.items() if i in saved["state"]}
    return {"state": state, "param_groups": groups}


# The process's RNG states, as tensors / plain lists, so train_state.pt loads with weights_only=True.
def rng_state() -> dict:
    s = np.random.get_state()
    v, internal, g = random.getstate()
    numpy = {"keys": torch.from_numpy(s[1].astype(np.int64)), "pos": int(s[2]), "gauss": [int(s[3]), float(s[4])]}
    return {"torch": torch.get_rng_state(), "numpy": numpy, "python": [v, list(internal), g],
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def set_rng_state(s: dict) -> None:
    torch.set_rng_state(s["torch"])
    if s.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(s["cuda"])
    n = s["numpy"]
    np.random.set_state(("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["gauss"][0], n["gauss"][1]))
    random.setstate((s["python"][0], tuple(s["python"][1]), s["python"][2]))
