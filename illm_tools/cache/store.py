"""AnnotationCache: reads and append-only writes of one annotation-cache directory.

Readers see exactly the shards listed in the manifest. Each shard is checked (sha256, size, schema,
row count) the first time this object reads it and its ``key`` column goes into a vectorised
in-memory index; ``refresh()`` picks up shards other writers have added since. Writers hold the
directory's flock for the whole write, so concurrent writers never lose each other's shards and
never store a key twice. The file format itself lives in ``layout``.
"""

from __future__ import annotations

import bisect
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from illm_tools.cache import layout
from illm_tools.cache.index import InvalidKeyError, KeyIndex, parse_keys
from illm_tools.cache.matrices import gather_matrix, merged, stacked
from illm_tools.errors import CacheError, SchemaError

SETUP_COLUMNS = ("task", "template_version", "renderer", "model", "model_fingerprint", "decoding", "history_len")
"""The columns that are the same for every key of one run's setup (the rest vary per state)."""


@dataclass
class AdoptReport:
    """What ``adopt_orphans`` did with the unlisted shards it found."""

    adopted: list[str] = field(default_factory=list)  # listed as they are
    rewritten: list[str] = field(default_factory=list)  # partly known: new rows went to a new shard
    removed: list[str] = field(default_factory=list)  # every key already present: deleted
    rejected: list[str] = field(default_factory=list)  # unreadable or wrong schema: left in place
    temp_removed: list[str] = field(default_factory=list)  # leftovers of crashed writes


class AnnotationCache:
    """One cache directory. ``root`` may not exist yet; it is created by the first write."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        layout.check_root(self.root)
        self.schema = layout.arrow_schema()
        self._reset()
        self.refresh()

    def _reset(self) -> None:
        self._index = KeyIndex()
        self._shards: list[dict] = []  # manifest entries, in index order
        self._starts: list[int] = []  # global row id of each shard's first row
        self._checked: set[tuple] = set()  # (name, inode, size, mtime_ns) of shards seen valid
        self._open: dict[int, tuple[tuple, pa.Table]] = {}  # every shard read so far, memory-mapped, with its stamp

    # ---- reading -------------------------------------------------------------------------

    def refresh(self) -> int:
        """Index shards the manifest gained since the last call; return how many."""
        listed = layout.read_manifest(self.root)["shards"]
        known = [s["name"] for s in self._shards]
        if [s["name"] for s in listed[: len(known)]] != known:
            self._reset()  # the manifest was rewritten (e.g. replaced by a copy): start over
        entries = listed[len(self._shards) :]
        keys = [self._read(entry).column("key") for entry in entries]  # all checked, or raise
        if keys:
            lengths = np.array([len(k) for k in keys])
            try:
                self._index.add(pa.chunked_array([c for k in keys for c in k.chunks], pa.string()))
            except InvalidKeyError as e:
                i = bisect.bisect_right(np.cumsum(lengths), e.position)
                row = e.position - int(lengths[:i].sum())
                raise CacheError(
                    f"shard {entries[i]['name']}: row {row} holds a malformed key; "
                    f"{layout.verify_hint(self.root)}"
                ) from e
            self._starts += (self._index.n_rows - lengths.sum() + np.cumsum(lengths) - lengths).tolist()
            self._shards += entries
        return len(entries)

    def _read(self, entry: dict) -> pa.Table:
        """Read a listed shard, refusing it unless it matches its manifest entry. The check
        (sha256 of the file) runs once per (name, inode, size, mtime) seen by this object."""
        name, path = entry["name"], self.root / entry["name"]
        stamp = self._stamp(path, name)
        if stamp not in self._checked:
            if stamp[2] != entry["bytes"] or layout.sha256_file(path) != entry["sha256"]:
                raise CacheError(
                    f"shard {name} is damaged (size or checksum differs from the manifest); "
                    f"{layout.verify_hint(self.root)}"
                )
        table = layout.read_shard(path)
        if stamp not in self._checked:
            layout.check_shard_schema(table.schema, f"shard {name}")
            if table.num_rows != entry["rows"]:
                raise CacheError(f"shard {name} has {table.num_rows} rows, manifest says {entry['rows']}")
            self._checked.add(stamp)
        return table

    def _stamp(self, path: Path, name: str) -> tuple:
        try:
            st = path.stat()
        except FileNotFoundError:
            raise CacheError(f"shard {name} is listed but missing; {layout.verify_hint(self.root)}") from None
        return (name, st.st_ino, st.st_size, st.st_mtime_ns)

    def _table(self, shard: int) -> pa.Table:
        """A listed shard, memory-mapped (kept: a mapping costs address space, not memory); re-read and
        re-checked if the file changed since it was opened."""
        entry = self._shards[shard]
        opened = self._open.get(shard)
        stamp = self._stamp(self.root / entry["name"], entry["name"])
        if opened is None or opened[0] != stamp:
            opened = self._open[shard] = (stamp, self._read(entry))
        return opened[1]

    def _gather(self, rows: np.ndarray, columns: Sequence[str]) -> pa.Table:
        """The given global rows (all >= 0), in that order, with the given columns. A large shard
        (`OWN_TAKE` rows or more) gives its rows by a take on its own column; the small shards the
        rows fall in give theirs by one take over their chunks together; the pieces are joined and
        put in the rows' order by one last take. Hand-written because pyarrow's take over a chunked
        list column joins every chunk first, a cost that grows with the cache, not with the rows
        asked for (2,048 states' look-up in a 409,600-row cache of 576-wide embeddings: 201 ms that
        way, 22 ms this way, pyarrow 26, docs/results/measured/trainer-pace.txt); and a take per
        shard costs about 0.1 ms each, too much for the hundreds of few-state shards that live
        annotation writes (`benchmarks/cache_lookup.py`). Each shard the rows fall in is read and
        checked once."""
        if not len(rows):
            return self.schema.empty_table().select(list(columns))
        groups = self._by_shard(rows)
        tables = {s: self._table(s) for s, _, _ in groups}  # a shard whose file changed is re-read and re-checked
        large = [g for g in groups if self._shards[g[0]]["rows"] >= OWN_TAKE]
        small = [g for g in groups if self._shards[g[0]]["rows"] < OWN_TAKE]
        picks = [positions for _, positions, _ in large]  # positions in `rows`, piece by piece
        if small:
            offsets = np.cumsum([0] + [tables[s].num_rows for s, _, _ in small])
            picks.append(np.concatenate([positions for _, positions, _ in small]))
            small_index = np.concatenate([local + offsets[k] for k, (_, _, local) in enumerate(small)])
        positions = np.concatenate(picks)
        back = None if np.array_equal(positions, np.arange(len(rows))) else np.argsort(positions)
        out = {}
        for name in columns:
            pieces = [_contiguous(tables[s].column(name)).take(pa.array(local)) for s, _, local in large]
            if small:
                chunks = [c for s, _, _ in small for c in tables[s].column(name).chunks]
                pieces.append(pa.chunked_array(chunks, self.schema.field(name).type).take(pa.array(small_index))
                              .combine_chunks())
            joined = pa.concat_arrays(pieces) if len(pieces) > 1 else pieces[0]
            out[name] = joined if back is None else joined.take(pa.array(back))
        return pa.table(out, schema=pa.schema([self.schema.field(name) for name in columns]))

    def _by_shard(self, rows: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """Global rows (all >= 0) grouped by the shard they fall in, in shard order: (shard, their
        positions in `rows`, their rows within the shard)."""
        starts = np.asarray(self._starts, np.int64)
        shard_of = np.searchsorted(starts, rows, "right") - 1
        order = np.argsort(shard_of, kind="stable")
        shards, first = np.unique(shard_of[order], return_index=True)
        bounds = np.append(first, len(order))
        local = rows - starts[shard_of]
        return [(int(s), order[bounds[i]:bounds[i + 1]], local[order[bounds[i]:bounds[i + 1]]]) for i, s in enumerate(shards)]

    def _found(self, keys, task: str | None) -> tuple[np.ndarray, np.ndarray]:
        rows = self._index.locate(keys)
        if task is not None:
            hit = np.flatnonzero(rows >= 0)
            tasks = self._gather(rows[hit], ["task"]).column("task").to_numpy(zero_copy_only=False)
            rows[hit[tasks != task]] = -1
        return rows, rows >= 0

    def contains(self, keys: Sequence[str]) -> np.ndarray:
        """Boolean mask: which keys the cache holds."""
        return self._index.locate(keys) >= 0

    def lookup(self, keys: Sequence[str], task: str | None = None) -> dict[str, dict]:
        """Full rows (plain Python values) of the keys found, optionally only of one task."""
        rows, found = self._found(keys, task)
        table = self._gather(rows[found], self.schema.names)
        return {row["key"]: row for row in table.to_pylist()}

    def get_columns(
        self, keys: Sequence[str], columns: Sequence[str], task: str | None = None
    ) -> dict[str, Any]:
        """Columns for the trainer, aligned with ``keys``; ``found`` is the bool mask of hits.

        ``embedding`` comes as np.float32 [n, d] (NaN rows where absent or null); every other
        column as a list with None where the key is absent.
        """
        self._known(columns)
        rows, found = self._found(keys, task)
        table = self._gather(rows[found], columns)
        out: dict[str, Any] = {"found": found}
        hit = np.flatnonzero(found)
        for name in columns:
            if name == "embedding":
                out[name] = stacked(table.column(name), hit, len(found), name)
                continue
            values: list = [None] * len(found)
            for i, v in zip(hit.tolist(), table.column(name).to_pylist()):
                values[i] = v
            out[name] = values
        return out

    def get_matrices(self, keys: Sequence[str], columns: Sequence[str], task: str | None = None) -> dict[str, Any]:
        """List-of-number columns (the embedding, the candidates' scores) aligned with ``keys``, each
        as np.float32 [n, d] with NaN rows where the key is absent or the value null (one d per
        column); ``found`` is the bool mask of hits. What the trainer reads every rollout: no
        Python object per value (the scores as lists cost a cached illm update 13 ms a look-up)."""
        self._known(columns)
        rows, found = self._found(keys, task)
        hit = np.flatnonzero(found)
        groups = self._by_shard(rows[hit])
        large = [(s, local, hit[at]) for s, at, local in groups if self._shards[s]["rows"] >= OWN_TAKE]
        few = np.concatenate([at for s, at, _ in groups if self._shards[s]["rows"] < OWN_TAKE] or [np.zeros(0, np.int64)])
        small = self._gather(rows[hit[few]], columns)  # few-state shards: one take over them together
        out: dict[str, Any] = {"found": found}
        for name in columns:
            big = gather_matrix(lambda shard: _contiguous(self._table(shard).column(name)), large, len(found), name)
            out[name] = merged(big, stacked(small.column(name), hit[few], len(found), name), hit[few], name)
        return out

    def _known(self, columns: Sequence[str]) -> None:
        unknown = sorted(set(columns) - set(self.schema.names))
        if unknown:
            raise CacheError(f"no columns {unknown} in the annotation schema")

    def __len__(self) -> int:
        return len(self._index)

    def shard_rows(self, name: str) -> int:
        """Rows of a listed shard (as of the last refresh)."""
        return next(s["rows"] for s in self._shards if s["name"] == name)

    def _distinct(self, columns: list[str]) -> pa.Table:
        """The given columns of every distinct key's row."""
        return self._gather(np.flatnonzero(self._index.first_rows()), columns)

    def table(self, columns: Sequence[str]) -> pa.Table:
        """The given columns of every distinct key's row (what `illm distil` reads of a teacher)."""
        self._known(columns)
        return self._distinct(list(columns))

    def setups(self) -> list[dict]:
        """The distinct setups the cache holds (the SETUP_COLUMNS every key of a run shares), each
        with its entry count and one of its prompts (from which a template layout can be read)."""
        rows = np.flatnonzero(self._index.first_rows())
        if not rows.size:
            return []
        table = self._gather(rows, list(SETUP_COLUMNS)).append_column("row", pa.array(rows))
        groups = table.group_by(list(SETUP_COLUMNS)).aggregate([("row", "min"), ("row", "count")])
        prompts = self._gather(groups.column("row_min").to_numpy(), ["prompt"]).column("prompt").to_pylist()
        out = []
        for group, prompt in zip(groups.to_pylist(), prompts):
            group["entries"] = group.pop("row_count")
            group.pop("row_min")
            out.append({**group, "prompt": prompt})
        return out

    def tasks(self) -> dict[str, int]:
        """Number of entries per task."""
        counts = self._distinct(["task"]).column("task").value_counts()
        return {c["values"].as_py(): c["counts"].as_py() for c in counts}

    def info(self) -> dict:
        """Summary for ``illm cache info``: entries per task and model, embedding dims, sizes."""
        t = self._distinct(["task", "model", "embedding_dim"])
        by = t.group_by(["task", "model"]).aggregate([("task", "count")])
        dims = pc.unique(t.column("embedding_dim").drop_null()).to_pylist()
        return {
            "root": str(self.root),
            "schema": f"{layout.KIND} v{self.schema.metadata[b'illm.version'].decode()}",
            "entries": len(self),
            "tasks": self.tasks(),
            "models": {f"{r['task']}/{r['model']}": r["task_count"] for r in by.to_pylist()},
            "embedding_dims": sorted(dims),
            "shards": len(self._shards),
            "bytes": sum(s["bytes"] for s in self._shards),
        }

    # ---- writing -------------------------------------------------------------------------

    def _checkpoint(self, stage: str) -> None:
        """Hook called at each stage of a write; tests replace it to simulate crashes."""

    def write(self, rows: list[dict] | pa.Table) -> str | None:
        """Append the rows whose keys are new as one shard; return its name (None if none new)."""
        table = layout.to_table(rows, self.schema)
        self.root.mkdir(parents=True, exist_ok=True)
        with layout.locked(self.root):
            return self._append(table)

    def _append(self, table: pa.Table) -> str | None:
        """Write under the lock: de-duplicate against the current manifest, then publish."""
        layout.check_root(self.root)
        self.refresh()
        new = np.zeros(table.num_rows, bool)
        full, _, _ = parse_keys(table.column("key"))
        new[np.unique(full, return_index=True)[1]] = True
        new &= ~self.contains(table.column("key"))
        if not new.any():
            return None
        table = table.filter(pa.array(new))
        entry = layout.write_shard(self.root, table, self._checkpoint)
        self._publish(entry)
        return entry["name"]

    def _publish(self, entry: dict) -> None:
        manifest = layout.read_manifest(self.root)
        manifest["shards"].append(entry)
        layout.write_manifest(self.root, manifest, self._checkpoint)
        self.refresh()

    def adopt_orphans(self) -> AdoptReport:
        """Repair after a crash: list valid unlisted shards, drop redundant ones and temp files."""
        report = AdoptReport()
        if not self.root.is_dir():
            return report
        with layout.locked(self.root):  # every writer holds it, so no write is in progress
            for name in layout.temp_files(self.root):
                (self.root / name).unlink()
                report.temp_removed.append(name)
            self.refresh()
            listed = {s["name"] for s in self._shards}
            for name in layout.shard_files(self.root):
                if name not in listed:
                    self._adopt(name, report)
        return report

    def _adopt(self, name: str, report: AdoptReport) -> None:
        path = self.root / name
        try:
            table = layout.read_shard(path)
            layout.check_shard_schema(table.schema, f"shard {name}")
            layout.to_table(table, self.schema)
        except (CacheError, SchemaError):
            report.rejected.append(name)
            return
        known = self.contains(table.column("key"))
        if known.all():
            path.unlink()
            report.removed.append(name)
        elif known.any() or len(set(table.column("key").to_pylist())) < table.num_rows:
            self._append(table)
            path.unlink()
            report.rewritten.append(name)
        else:
            size = path.stat().st_size
            self._publish(layout.manifest_entry(name, table.num_rows, layout.sha256_file(path), size))
            report.adopted.append(name)


OWN_TAKE = 1024
"""Rows from which a shard's rows are taken from it alone (`AnnotationCache._gather`)."""


def _contiguous(column: pa.ChunkedArray) -> pa.Array:
    """A shard's column as one array (a shard is written as one record batch: no copy then)."""
    return column.chunk(0) if column.num_chunks == 1 else column.combine_chunks()
