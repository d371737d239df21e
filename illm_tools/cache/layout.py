"""On-disk format of the annotation cache: file names, the manifest, the writer lock, shard I/O.

A cache is one directory::

    manifest.json                      what is visible: schema kind/version and, per shard,
                                       name, rows, sha256, bytes, created_unix
    shard-<UTC time>-<pid>-<uuid8>.arrow   Arrow IPC *stream* files, one schema (annotation v1)
    .lock                              flock'ed by a writer for the whole of one write
    .tmp-*                             a write in progress (or a crashed one; ignored by readers)

A shard is written to a temporary name, fsync'ed, renamed, and the directory fsync'ed; only then is
it appended to the manifest (itself replaced through temp file + fsync + rename). Everything here
is plain pyarrow, so the files can be read without illm.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

import schemas
from illm_tools import durable
from illm_tools.cache.index import parse_keys
from illm_tools.errors import CacheError, SchemaError
from illm_tools.folders import FORMAT, MANIFEST  # the stage markers live with `folders`

KIND = "annotation"
LOCK = ".lock"
TMP_PREFIX = ".tmp-"
SHARD_PREFIX, SHARD_SUFFIX = "shard-", ".arrow"

Checkpoint = Callable[[str], None]
"""Called with a stage name at each step of a write; tests use it to simulate crashes."""


def supported_versions() -> list[int]:
    return schemas.available().get(KIND, [])


def arrow_schema(version: int | None = None) -> pa.Schema:
    """The Arrow schema shards are written with (newest version unless told)."""
    return schemas.load(KIND, version).arrow


def verify_hint(root: Path) -> str:
    return f"run `illm cache verify {root}`"


def is_shard_name(name: str) -> bool:
    """A file name the cache writes its shards under: no folder in it (no separator, no `..`)."""
    return isinstance(name, str) and name.startswith(SHARD_PREFIX) and name.endswith(SHARD_SUFFIX) and \
        "/" not in name and "\\" not in name and ".." not in name


def shard_files(root: Path) -> list[str]:
    """Names of every shard file present, listed in the manifest or not."""
    return sorted(p.name for p in root.iterdir() if is_shard_name(p.name)) if root.is_dir() else []


def temp_files(root: Path) -> list[str]:
    return sorted(p.name for p in root.iterdir() if p.name.startswith(TMP_PREFIX)) if root.is_dir() else []


def check_root(root: Path) -> None:
    """Refuse a path that exists but is not a cache: never write into someone else's folder."""
    from illm_tools.folders import refuse_foreign

    refuse_foreign(root, "annotation cache", "--cache")
    if not root.exists() or (root / MANIFEST).exists():
        return
    if not root.is_dir():
        raise CacheError(f"{root} is a file, not an annotation cache directory")
    foreign = [
        p.name for p in root.iterdir()
        if not (is_shard_name(p.name) or p.name.startswith(TMP_PREFIX) or p.name == LOCK)
    ]
    if foreign:
        raise CacheError(
            f"{root} is not an annotation cache (no {MANIFEST}, holds {sorted(foreign)[:3]}); "
            "pick an empty or new folder"
        )


def empty_manifest() -> dict:
    return {"format": FORMAT, "kind": KIND, "version": supported_versions()[-1], "shards": []}


def read_manifest(root: Path) -> dict:
    """The manifest, checked for format, kind and version; an empty one if none exists yet."""
    path = root / MANIFEST
    if not path.exists():
        return empty_manifest()
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise CacheError(f"{path} cannot be read ({type(e).__name__}): run `illm cache repair {root} --drop-damaged` "
                         "to list the whole shards again") from e
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise CacheError(f"{path} is not an illm annotation-cache manifest")
    check_kind_version(manifest.get("kind"), manifest.get("version"), str(path))
    if not isinstance(manifest.get("shards"), list):
        raise CacheError(f"{path} has no shard list; {verify_hint(root)}")
    for entry in manifest["shards"]:
        if not isinstance(entry, dict) or not is_shard_name(entry.get("name")):
            name = entry.get("name") if isinstance(entry, dict) else entry
            raise CacheError(f"{path} lists {str(name)[:80]!r}, not a shard name of this cache (a file beside the "
                             f"manifest): run `illm cache repair {root} --drop-damaged` to list the whole shards again")
    return manifest


def check_kind_version(kind, version, where: str) -> None:
    """Refuse data of another kind or an unsupported version, saying what was found."""
    supported = supported_versions()
    try:
        ok = kind == KIND and int(version) in supported
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise SchemaError(
            f"{where} holds {kind!r} version {version!r}; this illm reads {KIND!r} "
            f"version(s) {supported}. Use an illm release that supports it or re-annotate."
        )


def check_shard_schema(found: pa.Schema, where: str) -> None:
    """Check a shard's Arrow schema: kind/version metadata, then the columns and types."""
    meta = found.metadata or {}
    kind = meta.get(schemas.KIND_KEY, b"").decode() or None
    version = meta.get(schemas.VERSION_KEY, b"").decode() or None
    check_kind_version(kind, version, where)
    expected = arrow_schema(int(version))
    if not found.remove_metadata().equals(expected.remove_metadata()):
        got = {f.name: str(f.type) for f in found}
        want = {f.name: str(f.type) for f in expected}
        diff = sorted(n for n in set(got) | set(want) if got.get(n) != want.get(n))
        raise CacheError(f"{where} does not match schema {KIND} v{version}: columns {diff} differ")


def _write_or_remove(path: Path, data: bytes) -> None:
    """Write `path` itself (a temporary name) and fsync it, removing it when the write fails (e.g. a
    full disk); `durable.commit` renames it."""
    with durable.staged(path, tmp=path) as fh:
        fh.write(data)


def write_manifest(root: Path, manifest: dict, checkpoint: Checkpoint | None = None) -> None:
    """Replace the manifest atomically: temp file, fsync, rename, fsync the directory (`illm_tools.durable`)."""
    tmp = root / f"{TMP_PREFIX}{MANIFEST}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    _write_or_remove(tmp, (json.dumps(manifest, indent=1) + "\n").encode())
    if checkpoint:
        checkpoint("manifest-temp-written")
    durable.commit(tmp, root / MANIFEST)


@contextlib.contextmanager
def locked(root: Path) -> Iterator[None]:
    """Hold the cache's exclusive writer lock (released by the OS if the process dies)."""
    with durable.exclusive(root / LOCK):
        yield


def shard_bytes(table: pa.Table) -> bytes:
    """Serialise a table as one Arrow IPC stream."""
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()


def write_shard(root: Path, table: pa.Table, checkpoint: Checkpoint | None = None) -> dict:
    """Write a complete shard under its final name; return its manifest entry (not yet listed)."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    name = f"{SHARD_PREFIX}{stamp}-{os.getpid()}-{uuid.uuid4().hex[:8]}{SHARD_SUFFIX}"
    data = shard_bytes(table)
    tmp = root / f"{TMP_PREFIX}{name}"
    _write_or_remove(tmp, data)
    if checkpoint:
        checkpoint("shard-temp-written")
    durable.commit(tmp, root / name)
    if checkpoint:
        checkpoint("shard-renamed")
    return manifest_entry(name, table.num_rows, hashlib.sha256(data).hexdigest(), len(data))


def manifest_entry(name: str, rows: int, sha256: str, size: int) -> dict:
    return {"name": name, "rows": rows, "sha256": sha256, "bytes": size, "created_unix": time.time()}


sha256_file = durable.sha256_file


def read_shard(path: Path) -> pa.Table:
    """Read a whole shard, memory-mapped (zero copy)."""
    try:
        with pa.memory_map(str(path)) as source:
            return pa.ipc.open_stream(source).read_all()
    except (OSError, pa.ArrowInvalid) as e:
        raise CacheError(f"shard {path.name} cannot be read as an Arrow stream ({e})") from e


def to_table(rows: list[dict] | pa.Table, schema: pa.Schema) -> pa.Table:
    """Rows as a table of exactly ``schema``, or a CacheError saying what does not fit."""
    names = schema.names
    if isinstance(rows, pa.Table):
        present = set(rows.column_names)
        missing, extra = set(names) - present, present - set(names)
    else:
        rows = list(rows)
        missing = {n for r in rows for n in names if n not in r}
        extra = {k for r in rows for k in r if k not in names}
    if missing or extra:
        raise CacheError(
            f"annotation rows do not match schema {KIND}: "
            f"missing columns {sorted(missing)}, unexpected columns {sorted(extra)}"
        )
    try:
        if isinstance(rows, pa.Table):
            table = rows.select(names).cast(schema).replace_schema_metadata(schema.metadata)
        else:
            table = pa.Table.from_pylist(rows, schema=schema)
    except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as e:
        raise CacheError(f"annotation rows do not fit schema {KIND}: {e}") from e
    nulls = [f.name for f in schema if not f.nullable and table.column(f.name).null_count]
    if nulls:
        raise CacheError(f"annotation rows have nulls in required columns {nulls}")
    _, _, valid = parse_keys(table.column("key"))
    if not valid.all():
        bad = table.column("key")[int(np.flatnonzero(~valid)[0])].as_py()
        raise CacheError(f"key {bad!r} is not a 64-character lowercase hex sha256")
    if pc.any(pc.equal(pc.utf8_length(table.column("task")), 0)).as_py():  # tasks are plug-ins: any name
        raise CacheError("every row needs a task name")
    emb, dim = table.column("embedding"), table.column("embedding_dim")
    lengths = pc.list_value_length(emb)
    mismatch = pc.or_kleene(pc.not_equal(pc.is_null(emb), pc.is_null(dim)), pc.not_equal(lengths, dim))
    if pc.any(mismatch).as_py():
        raise CacheError("embedding_dim differs from the length of embedding in some rows")
    return table
