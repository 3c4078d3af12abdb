"""The read path of a dataset folder (local or URI) as plain Arrow: what pretraining streams.

Shards hold plain Arrow types only, so the same columns come back from pyarrow, pandas and Ray Data
(`roken.ray_pool.read_ray_dataset`); hidden temporary files of a running writer are never listed.
"""
from __future__ import annotations

import pyarrow as pa
import pyarrow.dataset as pads

from . import fs

TABLES = ("episodes", "maps")


def open_dataset(location: str, table: str = "episodes") -> pads.Dataset:
    """A lazy pyarrow dataset over `location/table/*.parquet` (filters and column selection push down)."""
    if table not in TABLES:
        raise ValueError(f"table must be one of {TABLES}, got {table!r}")
    filesystem, _ = fs.resolve(location)
    files = [fs.resolve(f)[1] for f in fs.list_files(fs.join(location, table), ".parquet")]
    if not files:
        raise FileNotFoundError(f"{fs.join(location, table)}: no .parquet shards; is {location} a dataset folder "
                                f"(maps/, episodes/, manifest.json)?")
    try:
        return pads.dataset(files, format="parquet", filesystem=filesystem)
    except (pa.ArrowInvalid, OSError) as e:
        raise CorruptShard(location, e) from None


def read_table(location: str, table: str = "episodes", columns: list[str] | None = None,
               successful_only: bool = False) -> pa.Table:
    ds = open_dataset(location, table)
    flt = (pads.field("success") == True) if successful_only else None  # noqa: E712  (Arrow expression)
    try:
        return ds.to_table(columns=columns, filter=flt)
    except (pa.ArrowInvalid, OSError) as e:
        raise CorruptShard(location, e) from None


class CorruptShard(ValueError):
    """A shard that cannot be read: which one, and that re-running generate.py on the folder repairs it."""

    def __init__(self, location: str, e: Exception):
        shard = next((w.strip("'\".,:") for w in str(e).split() if w.strip("'\".,:").endswith(".parquet")), None)
        super().__init__(f"{location}: a shard cannot be read ({shard or str(e).splitlines()[0][:200]}: corrupt or cut "
                         f"short). Re-run the pipelines/generate.py command that made {location} on the same --out: "
                         f"it regenerates the unreadable shards and keeps the others")

