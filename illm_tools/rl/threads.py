"""The process's settings for a stretch of work: torch's thread count (the policy runs on one thread,
the LLM on more), and what Python's garbage collector scans while a run trains."""

from __future__ import annotations

import gc
from contextlib import contextmanager


@contextmanager
def torch_threads(n: int):
    """Run the block with `n` torch threads, then restore the count. Torch is imported here, not
    with the module: a run starts its live worker before this process imports torch
    (`illm_tools.rl.run.train`)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


YOUNG_THRESHOLD = 10_000
"""The collector's young-generation threshold while a run trains (Python's default: 700)."""


@contextmanager
def frozen_heap():
    """Run the block with the objects that exist now (torch's, the env pool's, the network's: about
    350,000 in a BabyAI run) left out of the garbage collector's passes (`gc.freeze`), and its young
    generation collected every `YOUNG_THRESHOLD` new objects rather than 700; then put both back.
    An iLLM rollout holds its 2,048 states, their histories and keys until the update; they outlive
    the collector's young generations, and every few updates that set off a full pass over every
    object, ~240 ms each (14 ms an update of `benchmarks/train.py`'s cached run, against none for
    ppo, whose objects die young). Frozen, a full pass reads only what the run made; the larger
    young generation then took the collector's time from 3.4-3.7 to 1.1-1.4 ms an update (171
    passes in a 20-update run, 9 after; ppo: none either way). A process that froze its own objects
    before keeps its freeze and its thresholds: this leaves them as they are."""
    if gc.get_freeze_count():
        yield
        return
    thresholds = gc.get_threshold()
    gc.freeze()
    gc.set_threshold(max(thresholds[0], YOUNG_THRESHOLD), *thresholds[1:])
    try:
        yield
    finally:
        gc.set_threshold(*thresholds)
        gc.unfreeze()
