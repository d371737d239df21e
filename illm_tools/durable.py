"""Durable writes, for every file illm writes: the new content goes to a temporary file beside the
target, which is flushed and fsynced, renamed over the target, and the folder fsynced. A crash at
any point leaves the old file or the new one, whole, never a mix; a write that fails (a full disk)
removes its temporary file and leaves the old file as it was. This is the annotation cache's write
path (`illm_tools.cache.layout`), shared: shards, manifests, checkpoints, configs, metrics, state
files, exports and reports all go through here.

- `write_bytes(path, data)` / `write_text(path, text)`: the whole file at once; `write_json(path,
  payload)` a small record (its keys sorted), its folder made first;
- `staged(path)`: a context manager yielding an open temporary file for writers that stream
  (torch.save, numpy, parquet); the file is fsynced on exit and removed if the block raises;
  `commit(tmp, path)` renames it over the target and fsyncs the folder (kept apart so a caller can
  do something in between: checkpoints keep the previous file, the cache hooks crash tests in);
- `fsync_dir(path)`: make a rename in `path` durable;
- `commit_folder(tmp, path)`: a folder built whole in a temporary sibling (its files fsynced,
  `fsync_files`) renamed into place, so it is complete or absent; the rename refuses a `path`
  another process already filled, which the caller may take as its own;
- `sha256_file(path)`: the hash of a file's bytes, for the records that say what was written;
- `exclusive(lock_path, busy=...)`: hold a folder's writer lock (flock, released by the OS if the
  process dies): waits for it, or with `busy` raises that message at once when another process
  holds it (a training run's folder: two trainers must not write one run).
Temporary names start with "." and end with ".tmp", so listings and cleanup tell them apart.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from illm_tools.errors import IllmError

TMP_SUFFIX = ".tmp"


class BusyError(IllmError):
    """Another process holds the lock `exclusive(..., busy=...)` asked for (its message says what to do)."""


def temp_path(path: Path, prefix: str = ".") -> Path:
    """A temporary name beside `path`, unique to this process and call."""
    return path.with_name(f"{prefix}{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}{TMP_SUFFIX}")


def fsync_dir(path: str | os.PathLike) -> None:
    """fsync a folder, so the renames in it survive a crash."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def staged(path: str | os.PathLike, mode: str = "wb", *, tmp: Path | None = None) -> Iterator[IO]:
    """An open temporary file beside `path` (or at `tmp`), flushed and fsynced when the block ends,
    removed if it raises; `handle.name` is its path, for `commit`."""
    path = Path(path)
    tmp = tmp or temp_path(path)
    try:
        with open(tmp, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def commit(tmp: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Rename a staged file over `path` and fsync the folder."""
    path = Path(path)
    os.replace(tmp, path)
    fsync_dir(path.parent)
    return path


def fsync_files(folder: str | os.PathLike) -> None:
    """fsync every file directly in `folder`, so renaming them (or it) leaves them whole."""
    for p in Path(folder).iterdir():
        if p.is_file():
            with open(p, "rb") as fh:
                os.fsync(fh.fileno())


def commit_folder(tmp: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Rename the folder `tmp`, its files fsynced here, to `path` and fsync the parent folder. Raises
    OSError where `path` exists and is not empty (os.rename never merges folders)."""
    path = Path(path)
    fsync_files(tmp)
    fsync_dir(tmp)
    os.rename(tmp, path)
    fsync_dir(path.parent)
    return path


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Replace `path` with `data`, durably (see the module docstring)."""
    with staged(path) as fh:
        fh.write(data)
    return commit(fh.name, path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Replace `path` with `text` (UTF-8), durably."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, payload: dict) -> Path:
    """Replace `path` with `payload` as JSON, keys sorted, durably; its folder is made if absent (a
    memo's or a record's first write into a cache)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text(path, json.dumps(payload, sort_keys=True))


def sha256_file(path: str | os.PathLike) -> str:
    """The sha256 of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


@contextlib.contextmanager
def exclusive(lock_path: str | os.PathLike, *, busy: str | None = None) -> Iterator[None]:
    """Hold an exclusive flock on `lock_path` (created if absent) for the block. Without `busy` it
    waits for other holders; with it, a held lock raises `BusyError(busy)` at once."""
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (fcntl.LOCK_NB if busy is not None else 0))
        except BlockingIOError:
            raise BusyError(busy) from None
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
