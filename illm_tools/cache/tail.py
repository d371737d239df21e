"""Every row of a cache, each listed shard read once, in manifest order, as the manifest grows: for
a reader that keeps its own index of the whole cache's content rather than looking keys up (the
`illm-shuffled` control's fixed permutation, `illm_tools.rl.targets.ShuffledKeys`), so that it
never reads the cache's files itself.

The manifest is read from disk on every call, not from an `AnnotationCache`'s index: a shard
another writer published since is read at once. A manifest that no longer starts with the shards
already read (rewritten, e.g. a copy merged in place) is read again from its first shard, and the
caller is told so, to start its index over.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from illm_tools.cache import layout


class ShardTail:
    """The rows of a cache's shards listed since the last `read` (see the module docstring)."""

    def __init__(self, root: str | os.PathLike, columns: Sequence[str]):
        self.root = Path(root)
        self.columns = list(columns)
        self.shards: list[str] = []
        """The shards read so far, in manifest order."""

    def read(self) -> tuple[bool, list[list[dict]]]:
        """(whether the manifest was rewritten and reading started over, the rows of each shard read
        now: a list per shard, in manifest order, with `columns` as plain Python values)."""
        listed = [entry["name"] for entry in layout.read_manifest(self.root)["shards"]]
        restarted = listed[:len(self.shards)] != self.shards
        if restarted:
            self.shards = []
        out = []
        for name in listed[len(self.shards):]:
            out.append(layout.read_shard(self.root / name).select(self.columns).to_pylist())
            self.shards.append(name)
        return restarted, out
