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

A shared file is a stranger's bytes, and Parquet compresses and dictionary-encodes: a 9 KiB file
can decode to gigabytes. So the import bounds what it decodes before any row is built: from the
file's metadata, each row group's values (numbers by their count, text by its uncompressed pages)
must fit in `MAX_GROUP_BYTES` (else the file is refused in one line, nothing written); then it
reads `READ_ROWS` rows at a time with every text column kept dictionary-encoded, measures each
row's decoded size from the dictionaries, leaves out (counted, by key) every row over
`MAX_ROW_BYTES`, and decodes and checks the rest at most `DECODE_BYTES` at a time.

Publishing on the Hugging Face Hub (where the network allows) goes through this file:
`datasets.Dataset.from_parquet("ann.parquet").push_to_hub("user/illm-ann")`, and back:
`datasets.load_dataset("user/illm-ann", split="train").to_parquet("ann.parquet")`, then
`illm cache import ann.parquet --into data/ann`.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
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
IMPORT_BYTES = 128 << 20
"""Checked rows held for one write at most (a write comes sooner when they reach this size)."""
READ_ROWS = 1024
"""Rows read and measured at a time."""
DECODE_BYTES = 32 << 20
"""The most text and numbers decoded and checked at a time (fewer rows of a batch when they are large)."""
MAX_ROW_BYTES = 256 << 10
"""The most one imported row may decode to (its texts' UTF-8 bytes and its numbers' bytes); an
annotation row holds a few KiB (prompt, history, an embedding of a few thousand floats)."""
EXPORT_GROUP_ROWS = 1024
"""Rows per row group of an exported file (what an import decodes at once stays small)."""
MAX_GROUP_BYTES = 512 << 20
"""The most one row group of an imported file may decode to before its rows are measured (a file
`export` writes has groups of `EXPORT_GROUP_ROWS` rows of a few KiB each)."""
_WIDTHS = {"BOOLEAN": 1, "INT32": 4, "FLOAT": 4, "INT64": 8, "DOUBLE": 8, "INT96": 12}


@dataclass
class ShareReport:
    path: str
    rows: int = 0
    """Rows exported, or rows in the imported file."""
    added: int = 0
    """Import: rows the cache lacked and now holds."""
    shards: int = 0
    too_large: list[str] = field(default_factory=list)
    """Import: the key (its first 64 characters) of each row left out, never decoded, for being over
    `MAX_ROW_BYTES`."""


def export(root: str | os.PathLike, out: str | os.PathLike, *, fmt: str = "parquet",
           overwrite: bool = False, transform: Callable | None = None) -> ShareReport:
    """Write a verified cache's rows to one Parquet file (see the module docstring); `transform` (a
    pyarrow table of a shard's rows -> the rows as the file holds them) is what the caller shares them
    as (`illm cache export`: `tasks.rows.shareable`, a served model's address-free identity)."""
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
            table = transform(table) if transform is not None else table
            writer.write_table(table.cast(schema), row_group_size=EXPORT_GROUP_ROWS)
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
    layer above gives it; nothing is checked without one). Rows over `MAX_ROW_BYTES` are left out
    before they are decoded (`ShareReport.too_large`); a row group over `MAX_GROUP_BYTES` refuses the
    file before anything is read."""
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"no file at {path}: pass a Parquet file written by `illm cache export`")
    try:
        meta = pq.ParquetFile(str(path)).metadata
        texts = _bounded(meta, path)
        parquet = pq.ParquetFile(str(path), read_dictionary=texts)
    except (OSError, pa.ArrowException) as e:
        raise CacheError(f"{path} is not a readable Parquet file ({str(e).splitlines()[0][:80]})") from None
    cache = AnnotationCache(into)  # refuses a folder that is not a cache
    report = ShareReport(str(into))
    before = len(cache)
    pending: list[pa.Table] = []
    held = [0, 0]  # rows and bytes in pending
    for batch in _batches(parquet, path):
        report.rows += batch.num_rows
        sizes = _row_bytes(batch)
        small = sizes <= MAX_ROW_BYTES
        if not small.all():
            report.too_large += _keys(batch.filter(pa.array(~small)))
            batch, sizes = batch.filter(pa.array(small)), sizes[small]
        for piece in _pieces(batch, sizes):
            table = pa.Table.from_batches([piece]).replace_schema_metadata(parquet.schema_arrow.metadata)
            table = _checked(table, path)
            if check is not None:
                table = check(table, cache)
            pending.append(table)
            held[0] += table.num_rows
            held[1] += table.nbytes
            if held[0] >= IMPORT_BATCH or held[1] >= IMPORT_BYTES:
                report.shards += _write(cache, pending)
                held = [0, 0]
    report.shards += _write(cache, pending)
    report.added = len(cache) - before
    return report


def _batches(parquet: pq.ParquetFile, path: Path):
    """The file's rows, `READ_ROWS` at a time (text dictionary-encoded, one row group at a time: a
    nested column's dictionary does not span groups); a page that does not decode refuses the file
    in one line."""
    batches = (b for i in range(parquet.num_row_groups)
               for b in parquet.iter_batches(batch_size=READ_ROWS, row_groups=[i]))
    while True:
        try:
            batch = next(batches, None)
        except (OSError, pa.ArrowException) as e:
            raise CacheError(f"{path} is not a readable Parquet file ({str(e).splitlines()[0][:80]}); the rows "
                             "before it were imported") from None
        if batch is None:
            return
        yield batch


def _pieces(batch: pa.RecordBatch, sizes: np.ndarray):
    """`batch` in runs of rows that decode to at most `DECODE_BYTES` together (at least one row each)."""
    ends = np.cumsum(sizes)
    start = 0
    while start < batch.num_rows:
        before = int(ends[start - 1]) if start else 0
        stop = max(int(np.searchsorted(ends, before + DECODE_BYTES, side="right")), start + 1)
        yield batch.slice(start, stop - start)
        start = stop


def _write(cache: AnnotationCache, pending: list[pa.Table]) -> int:
    """Write the checked rows held (emptying `pending`); 1 when a shard was written."""
    table = pa.concat_tables(pending) if pending else None
    pending.clear()
    return int(bool(table is not None and table.num_rows and cache.write(table)))


def _bounded(meta: pq.FileMetaData, path: Path) -> list[str]:
    """The file's text columns (to read dictionary-encoded), once every row group is known to decode
    to at most `MAX_GROUP_BYTES` before its rows are measured: numbers by their count (a dictionary
    of one value repeated still decodes to every copy), text by its uncompressed pages (a dictionary
    page once, and an index per value)."""
    texts = []
    for j in range(meta.num_columns):
        column = meta.schema.column(j)
        if column.physical_type == "BYTE_ARRAY":
            texts.append(column.path)
    for i in range(meta.num_row_groups):
        group = meta.row_group(i)
        size = 0
        for j in range(group.num_columns):
            chunk = group.column(j)
            kind = chunk.physical_type
            if kind == "BYTE_ARRAY":
                size += chunk.total_uncompressed_size + 4 * chunk.num_values
            else:
                width = _WIDTHS.get(kind) or max(meta.schema.column(j).length or 0, 1)
                size += max(chunk.total_uncompressed_size, width * chunk.num_values)
        if size > MAX_GROUP_BYTES:
            raise CacheError(f"{path}: its row group {i} decodes to {size / 2**20:,.0f} MiB, over the "
                             f"{MAX_GROUP_BYTES >> 20} MiB an import reads at once: write it again in row groups of "
                             f"{EXPORT_GROUP_ROWS:,} rows (`illm cache export` does; pyarrow: "
                             f"row_group_size={EXPORT_GROUP_ROWS}); nothing was imported")
    return texts


def _row_bytes(batch: pa.RecordBatch) -> np.ndarray:
    """What each row of `batch` decodes to, in bytes, measured without decoding its text."""
    total = np.zeros(batch.num_rows, np.int64)
    for column in batch.columns:
        total += _value_bytes(column)
    return total


def _value_bytes(array: pa.Array) -> np.ndarray:
    """Per value of `array`, the bytes it decodes to (a list: its items' together; null: 0)."""
    kind = array.type
    if pa.types.is_dictionary(kind):
        lengths = _value_bytes(array.dictionary)
        indices = array.indices
        if indices.null_count:
            indices = indices.fill_null(0)
        return lengths[indices.to_numpy()] if lengths.size else np.zeros(len(array), np.int64)
    if pa.types.is_list(kind) or pa.types.is_large_list(kind):  # a row's items: the running sum between its offsets
        ends = np.concatenate([[0], np.cumsum(_value_bytes(array.values))])
        offsets = array.offsets.to_numpy()
        return ends[offsets[1:]] - ends[offsets[:-1]]
    if pa.types.is_string(kind) or pa.types.is_binary(kind) or pa.types.is_large_string(kind) \
            or pa.types.is_large_binary(kind):
        lengths = pc.binary_length(array)
        return (lengths.fill_null(0) if lengths.null_count else lengths).to_numpy().astype(np.int64)
    try:
        width = max(kind.bit_width // 8, 1)
    except ValueError:  # not a type of the schema: its columns are refused next (`_checked`)
        width = 8
    return np.full(len(array), width, np.int64)


def _keys(batch: pa.RecordBatch) -> list[str]:
    """The first 64 bytes of each row's key (decoding no more of it)."""
    if "key" not in batch.schema.names:
        return ["?"] * batch.num_rows
    keys = batch.column(batch.schema.get_field_index("key"))
    kind = keys.type.value_type if pa.types.is_dictionary(keys.type) else keys.type
    if not (pa.types.is_string(kind) or pa.types.is_large_string(kind) or pa.types.is_binary(kind)
            or pa.types.is_large_binary(kind)):  # not a key column: its rows are refused by the schema check
        return ["?"] * batch.num_rows
    if pa.types.is_dictionary(keys.type):
        keys = pc.take(pc.binary_slice(keys.dictionary.cast(pa.binary()), 0, 64), keys.indices)
    else:
        keys = pc.binary_slice(keys.cast(pa.binary()), 0, 64)
    return [k.decode(errors="replace") if k is not None else "?" for k in keys.to_pylist()]
