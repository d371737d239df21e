"""How a forward pass is called under the installed transformers: the keyword its KV cache goes
under, the cache it returns, and autograd on or off. `scoring`, `packed` and `generation` call the
model through these, so a rename in transformers is followed in one place."""

from __future__ import annotations

import functools
from typing import Any


@functools.lru_cache(maxsize=1)
def _cache_name() -> str:
    """The keyword a causal LM's forward takes its KV cache under: `cache` since transformers 5.24
    (which warns on the older `past_key_values`), `past_key_values` before."""
    import inspect

    from transformers import LlamaForCausalLM

    return "cache" if "cache" in inspect.signature(LlamaForCausalLM.forward).parameters else "past_key_values"


def cache_kwargs(cache: Any) -> dict:
    """{keyword: cache} for a model's forward, under the name the installed transformers reads."""
    return {_cache_name(): cache}


def returned_cache(out: Any) -> Any:
    """The KV cache a forward returned (`out.cache` since transformers 5.24, `past_key_values` before)."""
    return out.cache if _cache_name() == "cache" else out.past_key_values


def forward_mode(grad: bool):
    """autograd on (training: `illm distil`) or inference mode (annotation, probing)."""
    import contextlib

    import torch

    return contextlib.nullcontext() if grad else torch.inference_mode()
