"""In-memory key index of the annotation cache: hex sha256 keys → global row ids, vectorised.

Rows are numbered globally in the order shards are added. The index keeps the first 16 hex
digits of each key as a sorted uint64 array (``np.searchsorted`` finds candidates) and the full
64-character keys in row order (``S64``) to confirm each match, so a prefix collision can never
return a wrong row. About 80 bytes per row; no Python object per key.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

KEY_CHARS = 64

_NIBBLE = np.full(256, 255, dtype=np.uint8)
_NIBBLE[np.frombuffer(b"0123456789", np.uint8)] = np.arange(10, dtype=np.uint8)
_NIBBLE[np.frombuffer(b"abcdef", np.uint8)] = np.arange(10, 16, dtype=np.uint8)
_SHIFTS = np.arange(60, -1, -4, dtype=np.uint64)
_NIBBLE.flags.writeable = False


def parse_keys(keys: Sequence[str] | pa.Array | pa.ChunkedArray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (full keys as ``S64``, uint64 prefixes, valid mask); invalid keys are masked out.

    A valid key is exactly 64 lowercase hex characters.
    """
    if isinstance(keys, pa.ChunkedArray):
        keys = keys.combine_chunks()
    arr = keys if isinstance(keys, pa.Array) else pa.array(list(keys), type=pa.string())
    arr = arr.cast(pa.string())
    n = len(arr)
    if n == 0:
        return np.empty(0, "S64"), np.empty(0, np.uint64), np.empty(0, bool)
    valid = (pc.binary_length(arr.fill_null("")).to_numpy(zero_copy_only=False) == KEY_CHARS)
    if not valid.all():
        arr = pc.if_else(pa.array(valid), arr, pa.scalar("0" * KEY_CHARS))
    offsets = np.frombuffer(arr.buffers()[1], np.int32, count=n + 1, offset=arr.offset * 4)
    data = np.frombuffer(arr.buffers()[2], np.uint8)
    chars = data[offsets[0] : offsets[0] + KEY_CHARS * n].reshape(n, KEY_CHARS)
    nibbles = _NIBBLE[chars]
    valid &= (nibbles != 255).all(axis=1)
    prefix = np.bitwise_or.reduce(nibbles[:, :16].astype(np.uint64) << _SHIFTS, axis=1)
    full = np.ascontiguousarray(chars).view("S64").reshape(n)
    return full, prefix, valid


class InvalidKeyError(ValueError):
    """A key that is not 64 lowercase hex characters; ``position`` is its row in the batch."""

    def __init__(self, position: int) -> None:
        super().__init__(f"row {position} holds a key that is not 64 lowercase hex characters")
        self.position = position


class KeyIndex:
    """Sorted key prefixes over all rows added so far; duplicates keep their first row."""

    def __init__(self) -> None:
        self._prefix = np.empty(0, np.uint64)  # sorted prefixes of the indexed (first) rows
        self._rows = np.empty(0, np.int64)  # global row id of each sorted prefix
        self._keys = np.empty(0, "S64")  # full keys in row order; grows by doubling
        self.n_rows = 0

    def __len__(self) -> int:
        """Number of distinct keys."""
        return len(self._rows)

    def locate(self, keys) -> np.ndarray:
        """Global row id of each key, -1 where absent (or not a valid key)."""
        full, prefix, valid = parse_keys(keys)
        return self._locate(full, prefix, valid)

    def _locate(self, full: np.ndarray, prefix: np.ndarray, valid: np.ndarray) -> np.ndarray:
        out = np.full(len(full), -1, np.int64)
        if not len(self._rows) or not len(full):
            return out
        lo = np.searchsorted(self._prefix, prefix, "left")
        hi = np.searchsorted(self._prefix, prefix, "right")
        stored = self._keys[: self.n_rows]
        single = np.flatnonzero(valid & (hi - lo == 1))
        rows = self._rows[lo[single]]
        match = stored[rows] == full[single]
        out[single[match]] = rows[match]
        for i in np.flatnonzero(valid & (hi - lo > 1)):  # prefix collision: practically never
            for j in range(lo[i], hi[i]):
                if stored[self._rows[j]] == full[i]:
                    out[i] = self._rows[j]
                    break
        return out

    def add(self, keys) -> np.ndarray:
        """Append a batch of rows (one shard); return the mask of rows that are new keys.

        Raises InvalidKeyError at the first key that is not 64 lowercase hex characters.
        """
        full, prefix, valid = parse_keys(keys)
        if not valid.all():
            raise InvalidKeyError(int(np.flatnonzero(~valid)[0]))
        new = np.zeros(len(full), bool)
        new[np.unique(full, return_index=True)[1]] = True
        new &= self._locate(full, prefix, valid) < 0
        ids = self.n_rows + np.flatnonzero(new)
        end = self.n_rows + len(full)
        if end > len(self._keys):
            grown = np.empty(max(end, 2 * len(self._keys)), "S64")
            grown[: self.n_rows] = self._keys[: self.n_rows]
            self._keys = grown
        self._keys[self.n_rows : end] = full
        self.n_rows = end
        order = np.argsort(prefix[new], kind="stable")
        at = np.searchsorted(self._prefix, prefix[new][order], "right")
        self._prefix = np.insert(self._prefix, at, prefix[new][order])
        self._rows = np.insert(self._rows, at, ids[order])
        return new

    def first_rows(self) -> np.ndarray:
        """Boolean mask over all rows: True for the row each distinct key resolves to."""
        mask = np.zeros(self.n_rows, bool)
        mask[self._rows] = True
        return mask
