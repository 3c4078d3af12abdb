"""Which torch device a stage runs on (training, the planner and GRPO pick it the same way)."""
from __future__ import annotations

import torch


def pick_device(name: str) -> torch.device:
    """"auto" = cuda where available; asking for cuda on a machine without it is said up front."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine; use --device cpu")
    return torch.device(name)
