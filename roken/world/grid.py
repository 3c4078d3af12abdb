"""A map as planned on: the canvas occupancy plus the derived fields every stage needs, computed once."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .geometry import inflate_free, pad_for_clearance, signed_distance_field
from .paths import GridGraph


@dataclass(eq=False)
class GridMap:
    map_id: str
    occupancy: np.ndarray  # (H, W) uint8, 1 = obstacle, already fitted to the canvas
    source: str = ""  # "generated:blocks", or the file it was loaded from
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        occ = np.asarray(self.occupancy)
        if occ.ndim != 2:
            raise ValueError(f"map {self.map_id}: occupancy must be 2-D, got shape {occ.shape}")
        self.occupancy = (occ != 0).astype(np.uint8)

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupancy.shape

    @cached_property
    def sdf(self) -> np.ndarray:
        """Signed distance at cell centres (float32, metres)."""
        return signed_distance_field(self.occupancy)

    @cached_property
    def padded(self) -> np.ndarray:
        """Occupancy padded for the exact clearance test."""
        return pad_for_clearance(self.occupancy)

    @cached_property
    def safe_cells(self) -> np.ndarray:
        """Cells whose 3 x 3 neighbourhood is free: centre clearance >= sqrt(2)."""
        return inflate_free(self.occupancy, 1)

    @cached_property
    def free_graph(self) -> GridGraph:
        """Octile graph of all free cells (the metric's A* length)."""
        return GridGraph.build(self.occupancy == 0)

    @cached_property
    def safe_graph(self) -> GridGraph:
        """Octile graph of the safe cells (the expert's reference paths, task placement)."""
        return GridGraph.build(self.safe_cells)
