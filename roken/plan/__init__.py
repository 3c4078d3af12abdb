"""Roken as a planner: one plan (RokenPlanner), closed-loop rollout (RokenRollout), the deployable planner one
re-plan at a time for user code (RokenController), clusters, selection, guidance."""
from .planner import RokenPlanner  # noqa: F401
from .rollout import PlanConfig, RokenRollout  # noqa: F401
from .controller import RokenController, Team  # noqa: F401
