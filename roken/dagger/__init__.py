"""DAgger with the Laplacian expert as relabeller: above `plan` (rollouts) and `train` (the mix)."""
from .relabel import DaggerConfig, relabel, select_states
from .rounds import run_dagger, summary_table

__all__ = ["DaggerConfig", "relabel", "select_states", "run_dagger", "summary_table"]
