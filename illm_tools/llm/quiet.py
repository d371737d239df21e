"""transformers kept quiet while it loads: its progress bars and warnings are not illm's output (a user
reads illm's own lines only). Used wherever a model is loaded: `loading`, `sentence`, the distillation."""

from __future__ import annotations

import functools
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def quiet_transformers() -> Iterator[None]:
    """Silence transformers' own progress bars and warnings (weight loading, GGUF de-quantising)
    while it loads: what a user reads is illm's output. Restores the previous settings."""
    import transformers.modeling_gguf_pytorch_utils as gguf_utils
    from transformers.utils import logging as hf_logging

    bars, verbosity = hf_logging.is_progress_bar_enabled(), hf_logging.get_verbosity()
    hf_logging.disable_progress_bar()
    hf_logging.set_verbosity_error()
    # the GGUF de-quantiser calls tqdm directly, past transformers' switch: its name there is
    # bound to a silenced tqdm for the load (there is no setting for it)
    own_tqdm = getattr(gguf_utils, "tqdm", None)
    if own_tqdm is not None:
        gguf_utils.tqdm = functools.partial(own_tqdm, disable=True)
    try:
        yield
    finally:
        if own_tqdm is not None:
            gguf_utils.tqdm = own_tqdm
        hf_logging.set_verbosity(verbosity)
        if bars:
            hf_logging.enable_progress_bar()
