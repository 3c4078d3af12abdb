"""Output locations as local paths or pyarrow filesystem URIs (s3://bucket/x, gs://bucket/x, file:///x).

Every writer in the project goes through `write_atomic`, so what a reader lists is always complete:
- on a local disk the bytes go to a hidden temporary name in the target folder and are renamed into place
  (rename is atomic on POSIX, and readers skip names starting with '.');
- on an object store (S3, GCS) an object only appears when its upload completes, so the file is built in
  memory first and sent in one upload: a crash mid-upload leaves no object, never a truncated one.
"""
from __future__ import annotations

import os
import uuid
from pathlib import Path

import pyarrow as pa
import pyarrow.fs as pafs


def is_uri(location: str | Path) -> bool:
    return "://" in str(location)


def resolve(location: str | Path) -> tuple[pafs.FileSystem, str]:
    """(filesystem, path inside it). A plain path is local and made absolute."""
    loc = str(location)
    if not is_uri(loc):
        return pafs.LocalFileSystem(), os.path.abspath(loc)
    try:
        return pafs.FileSystem.from_uri(loc)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, OSError) as e:
        raise OSError(f"{loc}: cannot open this location ({e}); use a local path or a URI such as "
                      f"s3://bucket/prefix, gs://bucket/prefix or file:///abs/path") from None


def join(location: str | Path, *parts: str) -> str:
    """Join path parts onto a local path or URI (pathlib would fold the '//' of a URI)."""
    loc = str(location)
    if not is_uri(loc):
        return str(Path(loc, *parts))
    base, sep, query = loc.partition("?")
    base = base.rstrip("/") + "/" + "/".join(p.strip("/") for p in parts)
    return base + sep + query


def exists(location: str | Path) -> bool:
    fs, path = resolve(location)
    return fs.get_file_info(path).type != pafs.FileType.NotFound


def list_files(folder: str | Path, suffix: str) -> list[str]:
    """Sorted locations of the visible files `*suffix` directly inside `folder` ([] if it is missing)."""
    fs, path = resolve(folder)
    infos = fs.get_file_info(pafs.FileSelector(path, allow_not_found=True))
    names = sorted(i.base_name for i in infos
                   if i.type == pafs.FileType.File and i.base_name.endswith(suffix)
                   and not i.base_name.startswith((".", "_")))
    return [join(folder, n) for n in names]


def read_bytes(location: str | Path) -> bytes:
    fs, path = resolve(location)
    with fs.open_input_stream(path) as f:
        return f.read()


def write_atomic(location: str | Path, data: bytes) -> str:
    """Write `data` so that `location` holds either nothing new or all of it."""
    fs, path = resolve(location)
    if isinstance(fs, pafs.LocalFileSystem):
        target = Path(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, target)
        finally:
            if tmp.exists():
                tmp.unlink()
        return str(location)
    parent = path.rsplit("/", 1)[0]
    if parent:
        fs.create_dir(parent, recursive=True)
    with fs.open_output_stream(path) as f:
        f.write(data)
    return str(location)


def remove(location: str | Path) -> None:
    """Delete the file at `location` if it is there."""
    fs, path = resolve(location)
    try:
        fs.delete_file(path)
    except FileNotFoundError:
        pass


def remove_empty_folder(location: str | Path) -> None:
    """Delete a local folder if it is empty (object stores have no folders to leave behind)."""
    fs, path = resolve(location)
    if isinstance(fs, pafs.LocalFileSystem):
        try:
            os.rmdir(path)
        except OSError:  # missing, or still holding files
            pass


def remove_stale_temporaries(folder: str | Path) -> int:
    """Delete temporary files a killed writer left in a local `folder`; returns how many."""
    fs, path = resolve(folder)
    if not isinstance(fs, pafs.LocalFileSystem) or not os.path.isdir(path):
        return 0
    stale = [p for p in Path(path).glob(".*.tmp")]
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)
