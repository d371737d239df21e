"""A training run's checkpoint: `run_dir/checkpoint.pt` and `checkpoint.prev.pt`, written by
`save_checkpoint` and read by `load_checkpoint` (a saved run is read through
`illm_tools.rl.saved.read_run`).

Checkpoints (format 2) hold the torch-saved state as bytes beside their sha256, so a damaged file
is detected, never loaded as other weights. A new checkpoint is written to a temporary file,
fsynced, and renamed over checkpoint.pt after the previous one was renamed to checkpoint.prev.pt
(the directory fsynced after each): at every moment one of the two is whole. `load_checkpoint`
falls back to the previous checkpoint, saying so, when the latest is missing or damaged. Format-1
checkpoints (no digest) still load.
"""

from __future__ import annotations

import hashlib
import io
import logging
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import torch

from illm_tools import durable
from illm_tools.errors import DamagedFileError, UsageError

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"
PREVIOUS_NAME = "checkpoint.prev.pt"
CHECKPOINT_VERSION = 2
READABLE_VERSIONS = (1, 2)
def save_checkpoint(run_dir: Path, state: dict) -> Path:
    """Write `state` to run_dir/checkpoint.pt with its digest, keeping the one it replaces as
    checkpoint.prev.pt (see the module docstring for the order of the renames)."""
    return _write(Path(run_dir), _serialise(state))


def _serialise(state: dict) -> bytes:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def _write(run_dir: Path, payload: bytes) -> Path:
    path, previous, tmp = run_dir / CHECKPOINT_NAME, run_dir / PREVIOUS_NAME, run_dir / f".{CHECKPOINT_NAME}.tmp"
    with durable.staged(path, tmp=tmp) as fh:  # e.g. a full disk: the checkpoints in place stay as they were
        torch.save({"format_version": CHECKPOINT_VERSION, "sha256": hashlib.sha256(payload).hexdigest(),
                    "state": payload}, fh)
    if path.exists():
        durable.commit(path, previous)
    return durable.commit(tmp, path)


class CheckpointWriter:
    """A run's checkpoints, written beside the training: `save(state, wait=False)` serialises the
    state at once (the tensors go on changing) and leaves the digest, the write, its fsync and the
    renames to a thread of its own, which releases the GIL for them; the next `save` and `wait` wait
    for it and raise what it raised. Hand-written around one thread because an illm run's checkpoint
    (the heads and their AdamW moments, 19 MB) took 107-132 ms a save written in line on a 2-core
    EPYC, most of it the write and fsync, 9 ms this way: in a 20-update run its first and last saves
    had been 11 ms an update."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)
        self._pending: Future | None = None

    def save(self, state: dict, *, wait: bool = True) -> None:
        self.wait()
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="illm-checkpoint")
        self._pending = pool.submit(_write, self.run_dir, _serialise(state))
        pool.shutdown(wait=False)  # its thread ends with this write: no idle thread outlives a run
        if wait:
            self.wait()

    def wait(self) -> None:
        """Until the checkpoint in flight, if any, is on disk (its error raised here)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()


def _read_checkpoint(path: Path) -> dict:
    """One checkpoint file's state; DamagedFileError (or UsageError for another format) if not whole."""
    try:
        outer = torch.load(path, map_location="cpu", weights_only=True)
        version = outer.get("format_version") if isinstance(outer, dict) else None
    except Exception as e:  # noqa: BLE001 - torch.load raises many kinds on a damaged file
        raise DamagedFileError(f"{path} is damaged ({type(e).__name__})") from None
    if version not in READABLE_VERSIONS:
        raise UsageError(f"{path} has checkpoint format {version!r}; this illm reads formats "
                         f"{', '.join(map(str, READABLE_VERSIONS))}")
    if version == 1:
        return outer
    payload = outer.get("state")
    if not isinstance(payload, bytes) or hashlib.sha256(payload).hexdigest() != outer.get("sha256"):
        raise DamagedFileError(f"{path} is damaged (its contents differ from their recorded sha256)")
    try:
        return torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001
        raise DamagedFileError(f"{path} is damaged ({type(e).__name__})") from None


_FALLBACKS_SAID: set[tuple] = set()


def load_checkpoint(run_dir: Path) -> dict:
    """The last whole checkpoint of a run: checkpoint.pt, or checkpoint.prev.pt (saying so) when
    the latest is missing or damaged. One line (UsageError / DamagedFileError) when neither is."""
    run_dir = Path(run_dir)
    path, previous = run_dir / CHECKPOINT_NAME, run_dir / PREVIOUS_NAME
    if not path.exists() and not previous.exists():
        raise UsageError(f"no checkpoint at {path}; train first or drop --resume")
    try:
        if not path.exists():
            raise DamagedFileError(f"{path} is missing")
        return _read_checkpoint(path)
    except DamagedFileError as latest:
        if not previous.exists():
            raise DamagedFileError(f"{latest}, and there is no previous checkpoint: train into a new --out") from None
        try:
            state = _read_checkpoint(previous)
        except DamagedFileError as prev:
            raise DamagedFileError(f"{latest}, and so is the previous one ({prev}): train into a new --out") from None
        said = (str(path), path.stat().st_mtime_ns if path.exists() else None)
        if said not in _FALLBACKS_SAID:  # a run reads its checkpoint more than once: say it once
            _FALLBACKS_SAID.add(said)
            log.warning("%s; using the previous checkpoint %s (update %s, %s frames)", latest, previous,
                        state.get("update"), f"{int(state.get('global_step', 0)):,}")
        return state
