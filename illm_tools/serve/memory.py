"""The server process's memory: its resident size (reported by /stats and watched by
benchmarks/serve_load.py) and the freed memory a batch leaves, handed back to the system."""

from __future__ import annotations

import os
from pathlib import Path


def release_free_memory() -> None:
    """Hand the memory a batch freed back to the system: glibc keeps freed blocks in its per-thread
    arenas, and a server that runs for days would otherwise creep up in resident size as batches of
    other shapes leave them fragmented. A no-op where the C library is not glibc."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def resident_mb() -> float | None:
    """This process's resident memory in MB (Linux's /proc; None elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
