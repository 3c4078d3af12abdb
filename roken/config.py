"""The root config: one typed section per stage, loaded from YAML with `--set` overrides."""
from __future__ import annotations

from dataclasses import dataclass, field

from .configtools import ConfigError, load, to_dict  # noqa: F401  (re-exported)
from .dagger.relabel import DaggerConfig
from .data.generation import DatasetConfig
from .data.samples import SampleConfig
from .eval.harness import EvalConfig
from .expert.laplacian import ExpertConfig
from .expert.gnn import GNNConfig
from .expert.sgg import SGGConfig
from .model.diffusion import DiffusionConfig
from .model.dit import ModelConfig
from .model.losses import LossConfig
from .plan.rollout import PlanConfig
from .rl.config import RLConfig
from .rl.selfcost import SelfCostConfig
from .train.loop import TrainConfig
from .world.maps import MapConfig
from .world.tasks import TaskConfig


@dataclass
class Config:
    map: MapConfig = field(default_factory=MapConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    sgg: SGGConfig = field(default_factory=SGGConfig)  # the SGG baseline (roken/expert/sgg.py)
    gnn: GNNConfig = field(default_factory=GNNConfig)  # the GNN baseline (roken/expert/gnn.py)
    eval: EvalConfig = field(default_factory=EvalConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    samples: SampleConfig = field(default_factory=SampleConfig)  # training samples cut from episodes
    model: ModelConfig = field(default_factory=ModelConfig)  # defaults = the `paper` preset
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)  # pretraining (roken/train/loop.py)
    plan: PlanConfig = field(default_factory=PlanConfig)  # Roken as a planner in closed loop (roken/plan)
    rl: RLConfig = field(default_factory=RLConfig)  # GRPO post-training (roken/rl)
    dagger: DaggerConfig = field(default_factory=DaggerConfig)  # DAgger rounds (roken/dagger)
    selfcost: SelfCostConfig = field(default_factory=SelfCostConfig)  # the cost of the model's own samples (roken/rl)


def load_config(path=None, overrides: list[str] | None = None) -> Config:
    return load(Config, path, overrides)
