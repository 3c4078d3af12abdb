"""Run logging on rank 0: metrics.jsonl (one JSON object per logged step), TensorBoard event files, and
progress lines with rate and ETA."""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path


def _clean(v):
    v = float(v)
    return v if math.isfinite(v) else None  # strict JSON: NaN / inf are written as null


class RunLogger:
    def __init__(self, run_dir: str | Path, enabled: bool = True, resume_step: int = 0, stream=None):
        self.enabled, self.stream = enabled, stream or sys.stderr
        self.path = Path(run_dir) / "metrics.jsonl"
        self.tb = None
        if not enabled:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():  # lines past the resumed step came from a run that died before its checkpoint
            kept = [ln for ln in self.path.read_text().splitlines() if _step_of(ln) <= resume_step]
            self.path.write_text("".join(ln + "\n" for ln in kept))
        self.file = self.path.open("a")
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:  # tensorboard is a dependency; a broken install still trains, with JSONL only
            print("note: tensorboard is not importable; metrics go to metrics.jsonl only", file=self.stream)
        else:
            self.tb = SummaryWriter(str(Path(run_dir) / "tb"), purge_step=resume_step + 1 if resume_step else None)

    def log(self, step: int, metrics: dict) -> None:
        if not self.enabled:
            return
        row = {"step": step, "time": round(time.time(), 3)} | {k: _clean(v) for k, v in metrics.items()}
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()
        if self.tb is not None:
            for k, v in metrics.items():
                if v is not None and math.isfinite(float(v)):
                    self.tb.add_scalar(k, float(v), step)

    def print(self, text: str) -> None:
        if self.enabled:
            self.stream.write(text + "\n")
            self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.file.close()
            if self.tb is not None:
                self.tb.close()


def _step_of(line: str) -> int:
    try:
        return int(json.loads(line).get("step", 0))
    except (ValueError, AttributeError):
        return 1 << 62  # an unreadable (cut) line is dropped


def duration(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = int(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"
