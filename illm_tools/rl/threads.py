"""Torch's thread count for a stretch of work (the policy runs on one thread, the LLM on more)."""

from __future__ import annotations

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
