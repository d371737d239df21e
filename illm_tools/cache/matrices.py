"""List-of-number columns (embeddings, the candidates' scores) read as float32 matrices.

`stacked` turns a gathered column into [n, d]; `gather_matrix` reads rows straight from each
large shard's memory-mapped values into one [n, d] array, without a take, a join and a conversion
in between. Hand-written because the look-up runs every rollout: 2,048 states' scores and 576-wide
embeddings from the train benchmark's 20-shard cache took 13 ms through pyarrow's take and Python
lists, 4.5 ms this way (docs/results/measured/trainer-pace.txt). Rows in small shards (live
annotation's few-state shards) are still taken through pyarrow, by one take over those shards
together (`AnnotationCache._gather`): a read per shard would cost more there."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from illm_tools.errors import CacheError


def stacked(column: pa.ChunkedArray, hit: np.ndarray, n: int, name: str) -> np.ndarray:
    """Stack a list<number> column's values (one per `hit` row) into float32 [n, d], NaN where
    absent or null; one d for all rows."""
    lengths = pc.unique(pc.list_value_length(column).drop_null()).to_pylist()
    if len(lengths) > 1:
        raise CacheError(f"{name} values of different sizes {sorted(lengths)}; select one model's keys")
    d = lengths[0] if lengths else 0
    out = np.full((n, d), np.nan, np.float32)
    arr = column.combine_chunks()
    present = ~arr.is_null().to_numpy(zero_copy_only=False)
    if d and present.any():
        values = pc.list_flatten(arr.filter(pa.array(present))).to_numpy().astype(np.float32)
        out[hit[present]] = values.reshape(-1, d)
    return out


def gather_matrix(column_of: Callable[[int], pa.Array], groups: Sequence[tuple[int, np.ndarray, np.ndarray]],
                  n: int, name: str) -> np.ndarray:
    """float32 [n, d] holding, for each (shard, local rows, out rows) of `groups`, the shard's list
    values of column `name` at its local rows in those out rows, and NaN rows elsewhere (absent,
    or null); `column_of(shard)` is a shard's column as one array. One d for all rows read."""
    parts, widths = [], set()
    for shard, at, to in groups:
        arr = column_of(shard)
        offsets = arr.offsets.to_numpy()
        start, length = offsets[at], offsets[at + 1] - offsets[at]
        present = ~arr.is_null().to_numpy(zero_copy_only=False)[at] if arr.null_count else np.ones(len(at), bool)
        widths.update(np.unique(length[present]).tolist())
        parts.append((to[present], start[present], arr.values))
    if len(widths) > 1:
        raise CacheError(f"{name} values of different sizes {sorted(widths)}; select one model's keys")
    d = widths.pop() if widths else 0
    out = np.full((n, d), np.nan, np.float32)
    for to, start, values in parts:
        if d and len(to):
            flat = values.to_numpy(zero_copy_only=False)
            if len(flat) % d == 0 and not (start % d).any():  # rows aligned on d: one row copy each
                out[to] = flat.reshape(-1, d)[start // d]
            else:
                out[to] = flat[start[:, None] + np.arange(d)]
    return out


def merged(a: np.ndarray, b: np.ndarray, rows_b: np.ndarray, name: str) -> np.ndarray:
    """`a` with `b`'s rows `rows_b` put in (the large shards' matrix and the small shards')."""
    if not len(rows_b) or not b.shape[1]:
        return a
    if not a.shape[1]:  # no value among the large shards' rows
        return b
    if a.shape[1] != b.shape[1]:
        raise CacheError(f"{name} values of different sizes {sorted({a.shape[1], b.shape[1]})}; select one model's keys")
    a[rows_b] = b[rows_b]
    return a
