"""Hub models on disk: the cached snapshot of a hub id, downloaded when the machine is online.

`snapshot(repo_names, fetch=...)` returns the snapshot folder (named by its commit, the revision
every fingerprint records). A snapshot already in the Hugging Face cache is used as it is, with no
network call, so a run's model does not change under it when the hub's `main` moves; a missing one
is downloaded through `huggingface_hub.snapshot_download` unless the machine is offline
(`HF_HUB_OFFLINE=1`, `--offline`) or the caller asked for no download (`no_downloads()`: listing
models and reading a cache's rows must never pull 16 GB).

Only what transformers loads is fetched: the top folder's config, tokenizer and weight files, and
`*.bin` weights only where the repository has no safetensors (a Llama repository also carries its
original checkpoint under `original/`, a GPT-2 one TF, Flax and ONNX copies). Before the download a
dry run asks the sizes, and too little free disk is refused in one line. The download's progress
is illm's own log line every `PROGRESS_EVERY_S` seconds (the hub's bars are silenced).

Failures are one line each (`ModelNotFoundError`): offline and not cached, a hub that cannot be
reached (the endpoint is named: `HF_ENDPOINT`), a gated repository without a token, an id that does
not exist, too little disk.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import os
import shutil
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from illm_tools.errors import ModelNotFoundError

log = logging.getLogger(__name__)

PROGRESS_EVERY_S = 15.0
"""Seconds between two progress lines of a download."""
_WANTED = ["*.json", "*.safetensors", "*.bin", "*.model", "*.txt", "*.jinja", "*.tiktoken"]
_SKIPPED = ["*/*"]  # sub-folders: original checkpoints, onnx/, other frameworks' copies
_NO_FETCH = contextvars.ContextVar("illm_hub_no_fetch", default=None)
"""Why nothing may be downloaded in this context (`no_downloads`), or None."""
_TOKEN_HINT = "set HF_TOKEN or run `hf auth login`"


def offline() -> bool:
    """True when the hub must not be asked: HF_HUB_OFFLINE (or TRANSFORMERS_OFFLINE) set, read at
    call time (huggingface_hub reads it once, at import)."""
    value = os.environ.get("HF_HUB_OFFLINE") or os.environ.get("TRANSFORMERS_OFFLINE") or ""
    return value.strip().upper() in {"1", "ON", "YES", "TRUE"}


@contextlib.contextmanager
def no_downloads(why: str = "illm does not download a model to list or describe it") -> Iterator[None]:
    """Within it, `snapshot` only looks in the cache (`--offline`; listing models, describing a
    cache's rows); `why` is said when a model is missing."""
    token = _NO_FETCH.set(why)
    try:
        yield
    finally:
        _NO_FETCH.reset(token)


def cache_dir() -> Path:
    """The Hugging Face hub cache folder, read at call time (HF_HUB_CACHE / HF_HOME honoured)."""
    from huggingface_hub import constants

    return Path(os.environ.get("HF_HUB_CACHE") or constants.HF_HUB_CACHE)


def endpoint() -> str:
    """The hub's address, read at call time (HF_ENDPOINT)."""
    from huggingface_hub import constants

    return (os.environ.get("HF_ENDPOINT") or constants.ENDPOINT).rstrip("/")


def cached(repo: str) -> Path | None:
    """The cached snapshot of `repo`'s main revision, or None (no network). Where the hub client
    recorded the repository's file list, every file `download` takes must be there (a download cut
    short is not a snapshot); `*.bin` weights are not asked for, as beside safetensors they are not
    taken."""
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError

    try:
        return Path(snapshot_download(repo, local_files_only=True, cache_dir=cache_dir(), allow_patterns=_WANTED,
                                      ignore_patterns=[*_SKIPPED, "*.bin"]))
    except (LocalEntryNotFoundError, FileNotFoundError, ValueError, OSError):  # IncompleteSnapshotError among them
        return None


def snapshot(names: Sequence[str]) -> Path:
    """The snapshot folder of the first of `names` (a hub id, then older names of the same
    repository) that is cached; otherwise the first name downloaded, where the machine is online
    and downloads are allowed. Raises `ModelNotFoundError` with one line that says what to do."""
    for repo in names:
        found = cached(repo)
        if found is not None:
            return found
    repo = names[0]
    why = _NO_FETCH.get() or ("HF_HUB_OFFLINE is set" if offline() else None)
    if why:
        raise ModelNotFoundError(
            f"model {repo!r} is not in the Hugging Face cache at {cache_dir()} and {why}: on a machine with network "
            f"run `hf download {repo}` (or `illm annotate` without --offline and HF_HUB_OFFLINE) and copy the cache "
            "folder here (or set HF_HUB_CACHE), or pass --model <local folder>")
    return download(repo)


def download(repo: str) -> Path:
    """Download `repo`'s main revision (what transformers loads) into the hub cache."""
    from huggingface_hub import snapshot_download
    from huggingface_hub.utils import disable_progress_bars, enable_progress_bars, are_progress_bars_disabled

    quiet = are_progress_bars_disabled()
    disable_progress_bars()
    try:
        with _hub_errors(repo):
            listed = snapshot_download(repo, cache_dir=cache_dir(), allow_patterns=_WANTED,
                                       ignore_patterns=_SKIPPED, dry_run=True, endpoint=endpoint())
            names = [f.filename for f in listed]
            if any(n.endswith(".safetensors") for n in names):
                listed = [f for f in listed if not f.filename.endswith(".bin")]
            if not any(f.filename.endswith((".safetensors", ".bin")) for f in listed):
                raise ModelNotFoundError(f"the hub repository {repo!r} has no safetensors or .bin weights in its top "
                                         "folder: it is not a transformers model (pass another id or a local folder)")
            need = sum(int(f.file_size or 0) for f in listed if f.will_download)
            _check_disk(repo, need)
            log.info("downloading %s from %s: %d files, %s (the hub cache: %s)", repo, endpoint(), len(listed),
                     _size(need), cache_dir())
            started = time.monotonic()
            folder = snapshot_download(repo, cache_dir=cache_dir(), allow_patterns=[f.filename for f in listed],
                                       tqdm_class=_progress_class(repo, need), endpoint=endpoint())
        log.info("downloaded %s in %.0f s -> %s", repo, time.monotonic() - started, folder)
        return Path(folder)
    finally:
        if not quiet:
            enable_progress_bars()


def _check_disk(repo: str, need: int) -> None:
    """Refuse a download that does not fit the free space (with a 5% margin)."""
    where = cache_dir()
    probe = where
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need * 1.05 > free:
        raise ModelNotFoundError(f"downloading {repo} needs {_size(need)} and {probe} has {_size(free)} free: free some "
                                 "space or set HF_HUB_CACHE to a folder on a larger disk")


@contextlib.contextmanager
def _hub_errors(repo: str) -> Iterator[None]:
    """The hub's failures as one line each (`ModelNotFoundError`); other errors pass."""
    from huggingface_hub.errors import DryRunError, LocalEntryNotFoundError

    try:
        yield
    except ModelNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 - mapped below, or raised as it is
        # a dry run (and a failed look-up in the cache) carries the hub's own error as its cause
        cause = e.__cause__ if isinstance(e, (DryRunError, LocalEntryNotFoundError)) and e.__cause__ else e
        message = _hub_message(repo, cause)
        if message is None:
            raise
        raise ModelNotFoundError(message) from None


def _hub_message(repo: str, e: BaseException) -> str | None:
    """The line that says what to do about the hub's error `e`, or None for an error of another kind."""
    from huggingface_hub.errors import (DryRunError, GatedRepoError, HfHubHTTPError, LocalEntryNotFoundError,
                                        RepositoryNotFoundError, RevisionNotFoundError)

    if isinstance(e, GatedRepoError):
        return (f"{repo} is a gated model: accept its licence on its page at {endpoint()}/{repo}, then {_TOKEN_HINT} "
                "with an account that was granted access")
    if isinstance(e, RepositoryNotFoundError):
        return (f"no model {repo!r} on the hub at {endpoint()} (or it is private: {_TOKEN_HINT}); check the id, or run "
                "`illm models` for the aliases")
    if isinstance(e, RevisionNotFoundError):
        return f"{repo} has no main revision on the hub at {endpoint()}"
    if isinstance(e, HfHubHTTPError):
        status = getattr(getattr(e, "response", None), "status_code", "?")
        if status == 401:
            return f"the hub at {endpoint()} refused {repo} without credentials (401): {_TOKEN_HINT}"
        return (f"the hub at {endpoint()} answered {status} for {repo}: try again later, or run offline with a cached "
                "model (HF_HUB_OFFLINE=1)")
    network = isinstance(e, (ConnectionError, TimeoutError, DryRunError, LocalEntryNotFoundError)) or \
        type(e).__module__.split(".")[0] in {"httpx", "httpcore", "httpx2"}  # httpx's errors are no OSError
    if network:
        return (f"the Hugging Face hub at {endpoint()} cannot be reached ({type(e).__name__}) and {repo} is not in the "
                f"cache at {cache_dir()}: check the network (or HF_ENDPOINT), then run again (what was downloaded is "
                "kept), or copy a cached snapshot here and set HF_HUB_OFFLINE=1")
    return None


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000
    return f"{n:.1f} GB"


def _progress_class(repo: str, total: int):
    """A tqdm class that says the download's bytes as illm's log line, every PROGRESS_EVERY_S seconds.
    The hub counts bytes on two bars (transferred, written; which one moves depends on the transfer
    protocol): the line says the larger; the file-count bar stays silent."""
    from tqdm import tqdm

    said = {"at": time.monotonic(), "bytes": 0}

    class DownloadProgress(tqdm):
        def __init__(self, *args, **kwargs):
            kwargs.pop("name", None)
            self._speaks = kwargs.get("unit") == "B"
            kwargs["file"] = open(os.devnull, "w")  # noqa: SIM115 - closed in close()
            kwargs["mininterval"] = 1.0
            super().__init__(*args, **kwargs)

        def display(self, msg=None, pos=None):
            if not self._speaks:
                return True
            said["bytes"] = max(said["bytes"], int(self.n))
            now = time.monotonic()
            if now - said["at"] >= PROGRESS_EVERY_S:
                rate = said["bytes"] / max(now - started, 1e-9)
                said["at"] = now
                log.info("downloading %s: %s of %s, %s/s", repo, _size(said["bytes"]), _size(total), _size(rate))
            return True

        def close(self):
            super().close()
            with contextlib.suppress(Exception):
                self.fp.close()

    started = time.monotonic()
    return DownloadProgress
