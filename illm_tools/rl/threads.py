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


@contextmanager
def frozen_heap():
    """Run the block with the objects that exist now (torch's, the env pool's, the network's: about
    350,000 in a BabyAI run) left out of the garbage collector's passes (`gc.freeze`), then put them
    back. An iLLM rollout holds its 2,048 states, their histories and keys until the update; they
    outlive the collector's young generations, and every few updates that set off a full pass over
    every object, ~240 ms each (14 ms an update of `benchmarks/train.py`'s cached run, against none
    for ppo, whose objects die young). Frozen, a full pass reads only what the run made. A process
    that froze its own objects before keeps its freeze: this leaves it as it is."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()
