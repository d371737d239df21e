"""Whole-cache checks, repairs and merges: ``verify`` (behind `illm cache verify`), ``drop_damaged``
(`illm cache repair --drop-damaged`) and ``merge``.

``verify`` reads every file and reports every problem it finds instead of stopping at the first;
``merge`` copies what a target lacks from verified sources through the target's ordinary atomic
write path, so a merge interrupted at any point leaves the target valid.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa

from illm_tools.cache import layout
from illm_tools.cache.index import InvalidKeyError, KeyIndex
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import CacheError, SchemaError, UsageError


@dataclass
class VerifyReport:
    """Outcome of ``verify``. ``ok`` is about the visible cache: orphans and temp files are
    leftovers of interrupted writes, reported but harmless (``adopt_orphans`` repairs them)."""

    root: str
    schema: str = ""
    shards: int = 0
    rows: int = 0
    keys: int = 0
    problems: list[str] = field(default_factory=list)
    orphans: list[str] = field(default_factory=list)
    temp_files: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


@dataclass
class MergeReport:
    """Outcome of ``merge``: per source, shards written into the target and rows copied/skipped."""

    into: str
    shards_written: list[str] = field(default_factory=list)
    rows_copied: int = 0
    rows_skipped: int = 0
    sources: dict[str, dict] = field(default_factory=dict)


def verify(root: str | os.PathLike) -> VerifyReport:
    """Check the manifest and every listed shard: checksum, size, schema, rows, duplicate keys."""
    root = Path(root)
    report = VerifyReport(root=str(root))
    if not (root / layout.MANIFEST).is_file():
        report.problems.append(f"{root} has no {layout.MANIFEST}: not an annotation cache")
        return report
    try:
        manifest = layout.read_manifest(root)
    except (CacheError, SchemaError) as e:
        report.problems.append(str(e))
        return report
    report.schema = f"{manifest['kind']} v{manifest['version']}"
    report.shards = len(manifest["shards"])
    index = KeyIndex()
    listed = set()
    for entry in manifest["shards"]:
        listed.add(entry.get("name"))
        problem = _check_shard(root, entry, index)
        if problem:
            report.problems.append(problem)
        else:
            report.rows += entry["rows"]
    if len(listed) < len(manifest["shards"]):
        report.problems.append("the manifest lists a shard more than once")
    report.keys = len(index)
    report.orphans = [n for n in layout.shard_files(root) if n not in listed]
    report.temp_files = layout.temp_files(root)
    return report


def _check_shard(root: Path, entry: dict, index: KeyIndex) -> str | None:
    """One listed shard's problem, or None; its keys go into ``index`` to find duplicates."""
    try:
        name = entry["name"]
        path = root / name
        if not path.is_file():
            return f"shard {name}: listed in the manifest but missing"
        size = path.stat().st_size
        if size != entry["bytes"]:
            return f"shard {name}: {size} bytes, manifest says {entry['bytes']} (truncated or altered)"
        if layout.sha256_file(path) != entry["sha256"]:
            return f"shard {name}: sha256 differs from the manifest (damaged)"
        table = layout.read_shard(path)
        layout.check_shard_schema(table.schema, f"shard {name}")
        if table.num_rows != entry["rows"]:
            return f"shard {name}: {table.num_rows} rows, manifest says {entry['rows']}"
        try:
            new = index.add(table.column("key"))
        except InvalidKeyError as e:
            return f"shard {name}: {e}"
    except (KeyError, TypeError) as e:
        return f"manifest entry {entry!r} is malformed ({e})"
    except (CacheError, SchemaError) as e:
        return str(e)
    if not new.all():
        return f"shard {name}: {int((~new).sum())} keys duplicate keys of earlier rows"
    return None


DAMAGED_DIR = "damaged"
"""Where `drop_damaged` moves the files it takes out of a cache (kept, never deleted)."""


@dataclass
class DropReport:
    """Outcome of ``drop_damaged``: shards taken out of the manifest (their files moved to
    ``damaged/``), the rows they listed, and whether the manifest itself had to be rebuilt."""

    dropped: list[str] = field(default_factory=list)
    rows_lost: int = 0
    manifest_rebuilt: bool = False


def drop_damaged(root: str | os.PathLike) -> DropReport:
    """Make a damaged cache usable again, losing only what is damaged: every listed shard that
    fails ``verify``'s checks is dropped from the manifest and its file moved to ``damaged/``. An
    unreadable manifest is moved there too and an empty one started, so that ``adopt_orphans``
    (run next by `illm cache repair`) lists every shard that reads back whole. The entries lost
    are annotated again by the next `illm annotate` or live fallback."""
    root = Path(root)
    report = DropReport()
    if not (root / layout.MANIFEST).is_file():
        raise UsageError(f"no annotation cache at {root}: nothing to repair")
    aside = root / DAMAGED_DIR
    stamp = time.strftime("%Y%m%d-%H%M%S")
    with layout.locked(root):
        try:
            manifest = layout.read_manifest(root)
        except (CacheError, SchemaError):
            aside.mkdir(exist_ok=True)
            os.replace(root / layout.MANIFEST, aside / f"{layout.MANIFEST}.{stamp}")
            layout.write_manifest(root, layout.empty_manifest())
            report.manifest_rebuilt = True
            return report
        index = KeyIndex()
        keep = []
        for entry in manifest["shards"]:
            if _check_shard(root, entry, index) is None:
                keep.append(entry)
                continue
            name = entry.get("name") if isinstance(entry, dict) else None
            report.dropped.append(str(name))
            report.rows_lost += int(entry.get("rows", 0)) if isinstance(entry, dict) else 0
            if isinstance(name, str) and (root / name).is_file():
                aside.mkdir(exist_ok=True)
                os.replace(root / name, aside / name)
        if report.dropped:
            manifest["shards"] = keep
            layout.write_manifest(root, manifest)
    return report


def merge(sources: list[str | os.PathLike], into: str | os.PathLike, check=None) -> MergeReport:
    """Copy into ``into`` every row of ``sources`` whose key it lacks. Sources are only read;
    a damaged source is refused before anything is written. ``check(table, cache)`` returns the rows
    of each shard that may enter (`illm_tools.tasks.rows`, given by the layer above)."""
    into = Path(into)
    resolved = {Path(s).resolve() for s in sources}
    if into.exists() and into.resolve() in resolved:
        raise UsageError(f"cannot merge {into} into itself")
    for src in map(Path, sources):
        report = verify(src)
        if not report.ok:
            raise CacheError(
                f"source {src} failed verification ({report.problems[0]}); "
                f"run `illm cache verify {src}`; nothing was merged"
            )
    target = AnnotationCache(into)  # refuses a folder that is not a cache
    out = MergeReport(into=str(into))
    for src in map(Path, sources):
        copied = skipped = 0
        for entry in layout.read_manifest(src)["shards"]:
            table = _read_verified(src, entry)
            checked = check(table, target) if check is not None else table
            name = target.write(checked) if checked.num_rows else None
            added = target.shard_rows(name) if name else 0
            copied, skipped = copied + added, skipped + table.num_rows - added
            if name:
                out.shards_written.append(name)
        out.sources[str(src)] = {"rows_copied": copied, "rows_skipped": skipped}
        out.rows_copied += copied
        out.rows_skipped += skipped
    return out


def _read_verified(root: Path, entry: dict) -> pa.Table:
    """Re-check a source shard as it is read (it may have changed since ``verify``)."""
    path = root / entry["name"]
    if layout.sha256_file(path) != entry["sha256"]:
        raise CacheError(f"source shard {path} changed during the merge; run `illm cache verify {root}`")
    return layout.read_shard(path)
