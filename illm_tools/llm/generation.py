"""Greedy generation with summary embeddings, and text embeddings.

Owns `greedy_from()` (the history-compression task's summaries, temperature 0, after prompts the
engine's driver prefilled: `illm_tools.llm.driver.generate`) and `embed_texts()`. Prompts run
through `scoring.extend`, the package's one way of feeding tokens through a KV cache with padding,
masks and position ids. The decoding steps (`greedy_from`) feed one token per row with the same masks and position ids,
but on a private copy of the prompt cache preallocated for the new tokens (no copy of the whole
cache per step), without log-softmax over the vocabulary, and with finished rows dropped from
the batch rather than fed filler tokens.

A summary's embedding is the mean of the last hidden layer (after the final norm) over the
summary's tokens, each attending to the prompt and the summary tokens before it: exactly one
forward over prompt + generated ids restricted to the generated positions, here computed as the
tokens are fed. The end-of-sequence token and anything after it are excluded; a generation
that ends at once is embedded by the hidden state of that end-of-sequence token instead.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.llm.loading import LoadedModel
from illm_tools.llm.budget import token_batches
from illm_tools.llm.forward import cache_kwargs
from illm_tools.llm.scoring import PrefixState, extend

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Generation:
    """One greedy continuation of a prompt."""

    text: str
    """Decoded generated tokens, special tokens removed (whitespace kept as generated)."""
    token_ids: list[int]
    """Generated tokens before the end-of-sequence token."""
    finished: bool
    """True when the model emitted end-of-sequence; False when max_new_tokens cut it."""
    embedding: np.ndarray
    """float32 [hidden_size]: mean last hidden state over the generated tokens."""


@functools.cache
def _buffer_layer():
    """The class of `_decode_cache`'s layers (defined on first use: transformers is imported lazily)."""
    from transformers.cache_utils import DynamicLayer

    class BufferLayer(DynamicLayer):
        """A `DynamicLayer` whose keys and values live in buffers allocated once with room for the
        new tokens, where `DynamicLayer` concatenates (a copy of the whole cache at every step).
        `keys`/`values` are views of the filled columns: attention sees the same tensors as before.
        Only what decoding uses is supported (update, batch_select_indices)."""

        def __init__(self, keys, values, room: int):
            super().__init__()
            self.length = keys.shape[-2]
            self._keys = keys.new_empty((*keys.shape[:2], self.length + room, keys.shape[3]))
            self._values = values.new_empty((*values.shape[:2], self.length + room, values.shape[3]))
            self._keys[:, :, :self.length], self._values[:, :, :self.length] = keys, values
            self.dtype, self.device, self.is_initialized = keys.dtype, keys.device, True
            self._views()

        def _views(self) -> None:
            self.keys, self.values = self._keys[:, :, :self.length], self._values[:, :, :self.length]

        def update(self, key_states, value_states, *args, **kwargs):
            end = self.length + key_states.shape[-2]
            self._keys[:, :, self.length:end] = key_states
            self._values[:, :, self.length:end] = value_states
            self.length = end
            self._views()
            return self.keys, self.values

        def batch_select_indices(self, indices) -> None:
            self._keys, self._values = self._keys[indices], self._values[indices]
            self._views()

        def _unsupported(self, *args, **kwargs):
            raise NotImplementedError("a decoding buffer only grows and drops rows")

        crop = batch_repeat_interleave = reorder_cache = reset = _unsupported

    return BufferLayer


def _decode_cache(state: PrefixState, room: int):
    """A private copy of `state`'s cache with room for `room` more tokens: preallocated when every
    layer is a plain growing one, else (e.g. sliding windows) a fork that grows as `extend`'s do."""
    import copy

    from transformers.cache_utils import DynamicLayer

    if not all(type(layer) is DynamicLayer and layer.is_initialized for layer in state.cache.layers):
        return state.fork().cache
    cache = copy.copy(state.cache)
    cache.layers = [_buffer_layer()(layer.keys, layer.values, room) for layer in state.cache.layers]
    return cache


def greedy_from(lm: LoadedModel, state: PrefixState, max_new_tokens: int, *,
                release: bool = False) -> list[tuple[list[int], bool, np.ndarray]]:
    """Greedy decoding after an already-computed prompt state (e.g. a shared prefix extended by
    each row's own suffix); per row: tokens, finished, embedding. `state` is left untouched, unless
    `release`: its cache's layers are then dropped once copied into the decoding buffer (a caller
    done with it holds one copy of the prompts' keys and values while decoding, not two).

    Each step feeds one token per row still decoding, with the mask and position ids `extend`
    would give it; the next token is the argmax of the logits (as transformers' greedy search).
    A row leaves the batch once it has emitted end-of-sequence (after that token is fed, when it
    is all the row generated), so finished rows cost nothing in later steps."""
    import torch
    import torch.nn.functional as F

    eos = set(lm.eos_ids)
    n = state.batch_size
    tokens: list[list[int]] = [[] for _ in range(n)]
    finished = [False] * n
    sums = torch.zeros((n, lm.hidden_size), dtype=torch.float64)
    rows = list(range(n))  # the original row of each batch row still decoding
    cache = _decode_cache(state, max_new_tokens)
    if release and cache.layers is not state.cache.layers:
        state.cache.layers = []
    width = state.attention_mask.shape[1]
    mask = F.pad(state.attention_mask, (0, max_new_tokens), value=1)  # every new column is a real token
    positions = state.lengths
    chosen = state.last_logprobs.max(dim=-1).indices.tolist()  # argmax; faster on CPU
    for step in range(max_new_tokens):
        keep, feed = [], []  # batch rows fed at this step, and their tokens
        for b, (i, token) in enumerate(zip(rows, chosen)):
            if finished[i]:  # fed its end-of-sequence token at the last step
                continue
            if token in eos:
                finished[i] = True
                if tokens[i]:
                    continue
                # an empty summary is embedded by its end-of-sequence token: feed it
            else:
                tokens[i].append(token)
            keep.append(b)
            feed.append(token)
        if not keep:
            break
        if len(keep) < len(rows):
            index = torch.tensor(keep, device=mask.device)
            cache.batch_select_indices(index)
            mask, positions, rows = mask[index], positions[index], [rows[b] for b in keep]
        with torch.inference_mode():
            out = lm.model(input_ids=torch.tensor(feed, device=lm.device)[:, None],
                           attention_mask=mask[:, :width + step + 1], position_ids=positions[:, None],
                           **cache_kwargs(cache), use_cache=True, logits_to_keep=1, output_hidden_states=True)
        sums.index_add_(0, torch.tensor(rows), out.hidden_states[-1][:, -1].double().cpu())
        chosen = out.logits[:, -1].max(dim=-1).indices.tolist()
        positions = positions + 1
    counts = torch.tensor([max(len(t), 1) for t in tokens], dtype=torch.float64)[:, None]
    embeddings = (sums / counts).to(torch.float32).numpy()
    return [(tokens[i], finished[i], embeddings[i].copy()) for i in range(n)]


def embed_texts(lm: LoadedModel, texts: Sequence[str], *, batch_size: int = 8) -> np.ndarray:
    """float32 [len(texts), hidden_size]: mean last hidden state over each text's own tokens
    (leading special tokens such as <bos> are fed but not pooled, unless the text is empty)."""
    import torch

    encoded = [lm.encode(t) for t in texts]
    if any(not ids for ids in encoded):
        raise UsageError("cannot embed an empty text with a tokenizer that adds no special tokens")
    out = np.zeros((len(texts), lm.hidden_size), dtype=np.float32)
    skip = len(lm.bos_ids)
    for batch in token_batches([len(ids) for ids in encoded], batch_size, lm.batch_tokens):
        state = extend(lm, [encoded[i] for i in batch], hidden=True)
        hidden = state.last_hidden.double()
        for row, i in enumerate(batch):
            own = len(encoded[i]) - skip if len(encoded[i]) > skip else len(encoded[i])
            out[i] = hidden[row, hidden.shape[1] - own:].mean(dim=0).to(torch.float32).cpu().numpy()
    return out
