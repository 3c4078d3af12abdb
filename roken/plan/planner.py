"""RokenPlanner: a trained checkpoint as a planner (paper: single robot, team, and conditional generation).

    planner = RokenPlanner.load("models/roken-cpu-four-dagger")        # a checkpoint dir or a run folder
    plan = planner.plan(occupancy, positions, leader=0, goal=(120, 30))   # (n, 16, 2) metres
    plan = planner.plan(occ, pos, 0, goal, fixed={2: path2})             # robot 2 follows path2 (16, 2) exactly
    cands = planner.plan(occ, pos, 0, goal, candidates=32)               # (32, n, 16, 2) from one batched call

A plan is `horizon` (16) chunk moves, the positions every `interval` (4) simulator steps, in the coordinates
of the occupancy given (1 cell = 1 m). A map that is not the model's canvas is fitted the way the map loaders
fit it (max-pooled down so obstacles never vanish, or scaled up by an integer, then centred) and the plan is
mapped back. `sample` is the batched core the closed-loop rollout and GRPO use: many prompts (conditions from
`roken.data.condition.build_condition`) x G candidates in one model call per denoising step. This is the
paper's planner (one sample, no shield); the deployable one (guidance, verified selection, the carried plan, clusters)
one re-plan at a time for user code is `roken.plan.controller.RokenController`.
"""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..configtools import from_dict
from ..data.condition import build_condition, decode_chunk
from ..data.samples import SampleConfig
from ..model.diffusion import COND_KEYS, DiffusionConfig, NoiseSchedule, ddim_sample, ddpm_sample, make_prompt
from ..model.dit import ModelConfig, RokenDiT
from ..devices import pick_device
from ..world.loaders import fit_to_canvas
from ..world.maps import place_on_canvas

DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}
SAMPLERS = ("ddim", "ddpm")


@dataclass
class CanvasFit:
    """A user's map fitted to the model's canvas the way the map loaders fit it (max-pooled down by an integer so
    obstacles never vanish, or scaled up by an integer, then centred), and positions mapped between the two frames."""
    occupancy: np.ndarray  # (S, S) uint8, the canvas the model and the closed loop see
    seen: np.ndarray | None  # (S, S) bool, the sensed cells on the canvas (None: the whole map is known)
    scale: float  # canvas metres per map metre
    offset: np.ndarray  # (2,) (x, y) of the map's corner on the canvas

    @classmethod
    def of(cls, occupancy: np.ndarray, canvas: int, seen: np.ndarray | None = None,
           rescale: bool = True) -> "CanvasFit":
        """rescale=False keeps 1 cell = 1 m (clearances, spacing and speeds in the map's own metres): the map is
        only centred on the canvas, and one larger than the canvas is refused."""
        occ = np.asarray(occupancy)
        if occ.shape == (canvas, canvas):
            return cls(occ, seen, 1.0, np.zeros(2))
        if not rescale:
            h, w = occ.shape
            if max(h, w) > canvas:
                raise ValueError(f"occupancy: a {h} x {w} m map is larger than the model's {canvas} x {canvas} m canvas; "
                                 f"pass the window around the team (its robots and goal inside it, in its coordinates), "
                                 f"or rescale=True to fit the map to the canvas as the map loaders do (every distance "
                                 f"on the canvas then shrinks by {int(np.ceil(max(h, w) / canvas))})")
            off = np.array([(canvas - w) // 2, (canvas - h) // 2], dtype=np.float64)
            if seen is not None:
                seen = place_on_canvas((~np.asarray(seen, bool)).astype(np.uint8), canvas) == 0
            return cls(place_on_canvas((occ != 0).astype(np.uint8), canvas), seen, 1.0, off)
        fitted, info = fit_to_canvas((occ != 0).astype(np.uint8), canvas, 4)
        scale = info["scale"]
        if scale < 1:  # max-pooled by an integer factor f (the last block padded with obstacle)
            f = int(round(1 / scale))
            h, w = -(-occ.shape[0] // f), -(-occ.shape[1] // f)
        else:
            h, w = occ.shape[0] * int(scale), occ.shape[1] * int(scale)
        if seen is not None:
            seen = fit_to_canvas((~np.asarray(seen, bool)).astype(np.uint8), canvas, 4)[0] == 0
        return cls(fitted, seen, scale, np.array([(canvas - w) // 2, (canvas - h) // 2], dtype=np.float64))

    def to_canvas(self, p) -> np.ndarray:
        return np.asarray(p, np.float64) * self.scale + self.offset

    def from_canvas(self, p) -> np.ndarray:
        return (np.asarray(p) - self.offset) / self.scale


class RokenPlanner:
    def __init__(self, model: RokenDiT, schedule: NoiseSchedule, samples: SampleConfig, device="cpu",
                 dtype: str = "fp32", source: str = ""):
        if dtype not in DTYPES:
            raise ValueError(f"--dtype {dtype!r}: choose one of {sorted(DTYPES)}")
        self.model, self.schedule, self.cfg, self.source = model.eval(), schedule, samples, source
        self.device = torch.device(device)
        self.dtype = dtype
        # weights stay fp32; bf16 / fp16 run under autocast (the samplers keep their arithmetic in fp32)
        self.amp = (torch.autocast(self.device.type, dtype=DTYPES[dtype]) if dtype != "fp32" else nullcontext())
        if self.device.type == "cpu":
            torch.set_flush_denormal(True)  # measured 4x on CPU: tiny activations otherwise go denormal

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | Path, device: str = "cpu", dtype: str = "fp32", which: str = "latest",
             task_max_step: float | None = None) -> "RokenPlanner":
        """A checkpoint directory, or a run folder's latest / best checkpoint (CheckpointError if unusable)."""
        from ..train.checkpoint import load

        dev = pick_device(device)
        ld = load(path, dev, which=which, task_max_step=task_max_step)
        return cls(ld.model, ld.schedule, ld.samples, dev, dtype, str(ld.path))

    @staticmethod
    def pack(path: str | Path, which: str = "latest", task_max_step: float | None = None) -> dict:
        """A checkpoint as bytes (config + weights): shipped once through Ray's object store, so rollout actors
        on other machines need no shared file system."""
        from ..train.checkpoint import CONFIG, WEIGHTS, cross_check, find, read_config

        d = find(path, which)
        cfg = read_config(d)
        cross_check(from_dict(ModelConfig, cfg["model"], "model."), from_dict(SampleConfig, cfg["samples"], "samples."),
                    task_max_step, str(d / CONFIG))
        return {"path": str(d), "config": cfg, "weights": (d / WEIGHTS).read_bytes()}

    @classmethod
    def unpack(cls, blob: dict, device: str = "cpu", dtype: str = "fp32") -> "RokenPlanner":
        from safetensors.torch import load as load_bytes

        from ..train.checkpoint import load_weights

        from ..train.checkpoint import CheckpointError

        cfg, dev = blob["config"], pick_device(device)
        model = RokenDiT(from_dict(ModelConfig, cfg["model"], "model."))
        try:
            weights = load_bytes(blob["weights"])
        except Exception as e:  # noqa: BLE001  (safetensors' own error type for a truncated or damaged file)
            raise CheckpointError(f"{blob['path']}/model.safetensors: not a readable safetensors file ({e}); the "
                                  f"checkpoint is corrupt or was cut short: re-export or re-train it") from None
        load_weights(model, weights, blob["path"])
        sched = NoiseSchedule(from_dict(DiffusionConfig, cfg["diffusion"], "diffusion."), dev)
        return cls(model.to(dev), sched, from_dict(SampleConfig, cfg["samples"], "samples."), dev, dtype, blob["path"])

    @property
    def max_robots(self) -> int:
        return self.cfg.max_robots

    def describe(self) -> str:
        return (f"{self.source} ({self.model.num_params() / 1e6:.1f}M params, {self.device.type}, {self.dtype}, "
                f"max_robots {self.max_robots})")

    # ------------------------------------------------------------------ batched core
    @torch.no_grad()
    def sample(self, conds: list[dict], candidates: int = 1, sampler: str = "ddim", steps: int = 10,
               generators: list[torch.Generator] | None = None, guide=None, guide_steps: int = 0,
               noise_scale: float = 1.0) -> np.ndarray:
        """conds: build_condition outputs with the same token count T; returns (B, G, T, H, 2) planned
        positions in metres (given robots exactly as given). generators: one per prompt (its candidates' noise
        comes from it alone, so a prompt's plan does not depend on the other prompts in the batch).
        noise_scale: the initial noise's standard deviation (< 1: a lower-temperature sample, nearer the mode)."""
        if sampler not in SAMPLERS:
            raise ValueError(f"--sampler {sampler!r}: choose one of {', '.join(SAMPLERS)}")
        G, dev = candidates, self.device
        batch = {k: torch.from_numpy(np.stack([c[k] for c in conds])).to(dev) for k in COND_KEYS + ("map", "chunk")}
        noise = None
        if generators is not None:
            def noise(shape):  # shape (B * G, T, H, 2): each prompt's G rows from its own generator
                return noise_scale * torch.cat([torch.randn((G,) + tuple(shape[1:]), generator=g) for g in generators])
        elif noise_scale != 1.0:
            def noise(shape):
                return noise_scale * torch.randn(tuple(shape))
        with self.amp:
            prompt = make_prompt(self.model, {k: batch[k] for k in COND_KEYS + ("map",)}, batch["chunk"], G)
            if sampler == "ddim":
                chunk = ddim_sample(self.model, self.schedule, prompt, steps=steps, noise=noise, guide=guide,
                                    guide_steps=guide_steps).chunk
            else:
                chunk = ddpm_sample(self.model, self.schedule, prompt, noise=noise).chunk
        chunk = chunk.float().cpu().numpy().reshape((len(conds), G) + chunk.shape[1:])
        start = np.stack([c["start"] for c in conds])[:, None]  # (B, 1, T, 2)
        out = decode_chunk(chunk, start, self.cfg).astype(np.float32)
        for b, c in enumerate(conds):  # conditioned robots: exactly as given (decoding a cumsum rounds)
            f = c["traj_mask"] > 0
            if f.any():
                out[b][:, f] = decode_chunk(c["chunk"][f], c["start"][f], self.cfg)[None]
        return out

    # ------------------------------------------------------------------ one plan for user code
    def plan(self, occupancy: np.ndarray, positions: np.ndarray, leader: int, goal, fixed: dict | None = None,
             candidates: int = 1, sampler: str = "ddim", steps: int = 10, seed: int | None = None,
             seen: np.ndarray | None = None, previous: np.ndarray | None = None) -> np.ndarray:
        """Plan for one team. occupancy (h, w), 1 = obstacle; positions (n, 2) metres (x along columns);
        leader: the robot given the goal (-1: none); fixed: {robot: (H, 2) positions} returned exactly;
        seen (h, w) bool: cells sensed so far (unseen shown as free); previous (n, 2): the positions one chunk
        move (samples.interval simulator steps) earlier, read by a model with model.prev_move (None: at rest).
        Returns (n, H, 2), or (G, n, H, 2) when candidates > 1."""
        occ = np.asarray(occupancy)
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        n, H, S = len(pos), self.cfg.horizon, self.cfg.canvas
        if n > self.max_robots:
            raise ValueError(f"{n} robots, but this model has {self.max_robots} robot tokens (samples.max_robots); "
                             f"plan larger teams with clustered rollout (RokenController, plan.cluster_size=4)")
        fit = CanvasFit.of(occ, S, seen)
        occ, seen, to_canvas = fit.occupancy, fit.seen, fit.to_canvas
        fixed_mask, given = np.zeros(n, bool), np.zeros((n, H, 2), np.float32)
        for r, path in (fixed or {}).items():
            path = np.asarray(path, dtype=np.float64)
            if path.shape != (H, 2):
                raise ValueError(f"fixed[{r}] has shape {path.shape}; a given trajectory is ({H}, 2) positions")
            fixed_mask[r], given[r] = True, to_canvas(path)
        cond = build_condition(occ, to_canvas(pos), leader, None if goal is None else to_canvas(goal), self.cfg,
                               given=given, fixed=fixed_mask, seen=seen, tokens=n,
                               previous=None if previous is None else to_canvas(np.reshape(previous, (n, 2))))
        gen = torch.Generator().manual_seed(int(seed)) if seed is not None else None
        out = self.sample([cond], candidates, sampler, steps, [gen] if gen is not None else None)[0, :, :n]
        out = fit.from_canvas(out)
        for r, path in (fixed or {}).items():
            out[:, r] = path
        return out if candidates > 1 else out[0]
