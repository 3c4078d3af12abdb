"""Roken as a planner: one plan (RokenPlanner), closed-loop rollout (RokenRollout), clusters, selection."""
from .planner import RokenPlanner  # noqa: F401
from .rollout import PlanConfig, RokenRollout  # noqa: F401
