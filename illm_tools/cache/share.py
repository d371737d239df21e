"""Sharing a cache: export to one Parquet file, import one back (or a Hugging Face dataset's).

`export` verifies the cache first (a damaged cache is refused before anything is written), then
writes every row of every listed shard to one Parquet file, the annotation schema's kind and
version in its metadata, atomically (a temp file renamed into place; an existing file is kept
unless `overwrite`). `import_parquet` reads such a file, checks it is annotation rows of a version
this illm reads (or, for a file that lost the metadata on a round trip through `datasets`, that
its columns are exactly the schema's), and writes it into a cache through the cache's locked
append in batches, so keys already present are skipped and none is stored twice. Entries from
another model, template or renderer keep their own keys, so imported setups sit beside the
cache's own (`illm cache info` lists them).

Publishing on the Hugging Face Hub (where the network allows) goes through this file:
`datasets.Dataset.from_parquet("ann.parquet").push_to_hub("user/illm-ann")`, and back:
`datasets.load_dataset("user/illm-ann", split="train").to_parquet("ann.parquet")`, then
`illm cache import ann.parquet --into data/ann`.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from illm_tools import durable
from illm_tools.cache import layout
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import CacheError, OutputExistsError, SchemaError, UsageError

FORMATS = ("parquet",)
SUFFIXES = {"parquet": (".parquet", ".pq")}
"""The file names each format's files may carry: `--out` with another suffix is refused."""
IMPORT_BATCH = 50_000
"""Rows per write when importing (one shard each, at most)."""


@dataclass
class ShareReport:
    path: str
    rows: int = 0
    """Rows exported, or rows in the imported file."""
    added: int = 0
    """Import: rows the cache lacked and now holds."""
    shards: int = 0


def export(root: str | os.PathLike, out: str | os.PathLike, *, fmt: str = "parquet",
           overwrite: bool = False) -> ShareReport:
    """Write a verified cache's rows to one Parquet file (see the module docstring)."""
    from illm_tools.cache.verify import verify

    root, out = Path(root), Path(out)
    if fmt not in FORMATS:
        raise UsageError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    suffixes = SUFFIXES[fmt]
    if out.suffix and out.suffix.lower() not in suffixes:  # a file named .arrow must not hold Parquet
        raise UsageError(f"--out {out} is named {out.suffix}, and --format {fmt} writes {fmt.capitalize()}: name the "
                         f"file {' or '.join(suffixes)}")
    if out.exists() and not overwrite:
        raise OutputExistsError(f"{out} exists: pass --overwrite to replace it, or another --out")
    report = verify(root)
    if not report.ok:
        raise CacheError(f"{root} failed verification ({report.problems[0]}): run `illm cache verify {root}`; "
                         "nothing was exported")
    manifest = layout.read_manifest(root)
    schema = layout.arrow_schema(int(manifest["version"]))
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = 0
    with durable.staged(out) as fh, pq.ParquetWriter(fh, schema, compression="zstd") as writer:
        for entry in manifest["shards"]:
            table = layout.read_shard(root / entry["name"])
            writer.write_table(table.cast(schema))
            rows += table.num_rows
    durable.commit(fh.name, out)
    return ShareReport(str(out), rows=rows, shards=len(manifest["shards"]))


def _checked(table: pa.Table, where: Path) -> pa.Table:
    meta = table.schema.metadata or {}
    kind = meta.get(schemas.KIND_KEY, b"").decode() or None
    if kind is not None:
        layout.check_kind_version(kind, meta.get(schemas.VERSION_KEY, b"").decode(), str(where))
        schema = layout.arrow_schema(int(meta[schemas.VERSION_KEY].decode()))
    else:  # e.g. written back by `datasets`, which keeps the columns but not illm's metadata
        schema = layout.arrow_schema()
    if sorted(table.column_names) != sorted(schema.names):
        raise SchemaError(f"{where} does not hold annotation rows: columns {sorted(table.column_names)}, expected "
                          f"{sorted(schema.names)}")
    try:
        return table.select(schema.names).cast(schema)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as e:
        raise SchemaError(f"{where}: its columns do not have the annotation schema's types "
                          f"({str(e).splitlines()[0][:100]})") from None


def import_parquet(path: str | os.PathLike, into: str | os.PathLike,
                   check: Callable[[pa.Table, AnnotationCache], pa.Table] | None = None) -> ShareReport:
    """Add a Parquet file's annotation rows to a cache (created if absent); keys it holds are skipped.
    `check(table, cache)` returns the rows of each batch that may enter (`illm_tools.tasks.rows`: the
    layer above gives it; nothing is checked without one)."""
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"no file at {path}: pass a Parquet file written by `illm cache export`")
    try:
        parquet = pq.ParquetFile(str(path))
    except (OSError, pa.ArrowException) as e:
        raise CacheError(f"{path} is not a readable Parquet file ({str(e).splitlines()[0][:80]})") from None
    cache = AnnotationCache(into)  # refuses a folder that is not a cache
    report = ShareReport(str(into))
    before = len(cache)
    for batch in parquet.iter_batches(batch_size=IMPORT_BATCH):
        table = _checked(pa.Table.from_batches([batch]).replace_schema_metadata(parquet.schema_arrow.metadata), path)
        report.rows += table.num_rows
        if check is not None:
            table = check(table, cache)
        if table.num_rows and cache.write(table):
            report.shards += 1
    report.added = len(cache) - before
    return report
