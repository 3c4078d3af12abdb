"""Periodic progress lines with rate and ETA, and a fixed-width summary table (no extra dependency)."""
from __future__ import annotations

import sys
import time


class Progress:
    """Prints `label done/total rate ETA` at most every `every` seconds, and once at the end."""

    def __init__(self, total: int, label: str, unit: str = "ep", every: float = 2.0, stream=None):
        self.total, self.label, self.unit, self.every = total, label, unit, every
        self.stream = stream or sys.stderr
        self.done = 0
        self.t0 = self.last = time.perf_counter()

    def update(self, n: int = 1) -> None:
        self.done += n
        now = time.perf_counter()
        if now - self.last >= self.every or self.done >= self.total:
            self.last = now
            self.stream.write(self.line() + "\n")
            self.stream.flush()

    @property
    def rate(self) -> float:
        return self.done / max(time.perf_counter() - self.t0, 1e-9)

    def line(self) -> str:
        rate = self.rate
        eta = (self.total - self.done) / rate if rate > 0 else float("inf")
        pct = 100.0 * self.done / max(self.total, 1)
        return (f"{self.label} {self.done}/{self.total} ({pct:5.1f}%) {rate:6.1f} {self.unit}/s "
                f"ETA {eta:6.1f}s")
