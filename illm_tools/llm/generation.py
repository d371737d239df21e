"""Greedy generation with summary embeddings, and text embeddings.

Owns `generate()` (the history-compression task's summaries: temperature 0, batched, left-padded
prompts sorted by length) and `embed_texts()`. Both run on `scoring.extend`, the package's one
way of feeding tokens through a KV cache with padding, masks and position ids.

A summary's embedding is the mean of the last hidden layer (after the final norm) over the
summary's tokens, each attending to the prompt and the summary tokens before it: exactly one
forward over prompt + generated ids restricted to the generated positions, here computed as the
tokens are fed. The end-of-sequence token and anything after it are excluded; a generation
that ends at once is embedded by the hidden state of that end-of-sequence token instead.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.llm.loading import LoadedModel
from illm_tools.llm.scoring import PrefixState, extend, length_batches

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


def _greedy(lm: LoadedModel, prompts: list[list[int]], max_new_tokens: int) -> list[tuple[list[int], bool, np.ndarray]]:
    """Greedy decoding of one left-padded batch; per row: tokens, finished, embedding."""
    return greedy_from(lm, extend(lm, prompts), max_new_tokens)


def greedy_from(lm: LoadedModel, state: PrefixState, max_new_tokens: int) -> list[tuple[list[int], bool, np.ndarray]]:
    """Greedy decoding after an already-computed prompt state (e.g. a shared prefix extended by
    each row's own suffix); per row: tokens, finished, embedding."""
    import torch

    eos = set(lm.eos_ids)
    filler = lm.eos_ids[0] if lm.eos_ids else lm.pad_id
    n = state.batch_size
    tokens: list[list[int]] = [[] for _ in range(n)]
    sums = [torch.zeros(lm.hidden_size, dtype=torch.float64) for _ in range(n)]
    done, finished = [False] * n, [False] * n
    for _ in range(max_new_tokens):
        chosen = state.last_logprobs.argmax(dim=-1).tolist()
        feed, record = [], []
        for i, token in enumerate(chosen):
            if done[i]:  # finished rows are fed a filler token whose outputs are ignored
                feed.append([filler])
                record.append(False)
                continue
            if token in eos:
                done[i] = finished[i] = True
                record.append(not tokens[i])  # empty summary: embed the EOS token itself
            else:
                tokens[i].append(token)
                record.append(True)
            feed.append([token])
        if not any(record):
            break
        state = extend(lm, feed, past=state, hidden=True)
        last = state.last_hidden[:, -1].double().cpu()
        for i in range(n):
            if record[i]:
                sums[i] += last[i]
        if all(done):
            break
    out = []
    for i in range(n):
        count = max(len(tokens[i]), 1)
        out.append((tokens[i], finished[i], (sums[i] / count).to(torch.float32).numpy()))
    return out


def generate(lm: LoadedModel, prompts: Sequence[str], *, max_new_tokens: int = 64,
             batch_size: int = 8) -> list[Generation]:
    """Greedy (temperature 0) continuations of `prompts`, in order, with summary embeddings."""
    if max_new_tokens < 1:
        raise UsageError("max_new_tokens must be at least 1")
    encoded = [lm.encode(p) for p in prompts]
    if any(not ids for ids in encoded):
        raise UsageError("cannot generate from an empty prompt")
    results: list[Generation | None] = [None] * len(encoded)
    for batch in length_batches([len(ids) for ids in encoded], batch_size):
        for i, (ids, finished, emb) in zip(batch, _greedy(lm, [encoded[i] for i in batch], max_new_tokens)):
            text = lm.tokenizer.decode(ids, skip_special_tokens=True)
            results[i] = Generation(text, ids, finished, emb)
    return results  # type: ignore[return-value]


def embed_texts(lm: LoadedModel, texts: Sequence[str], *, batch_size: int = 8) -> np.ndarray:
    """float32 [len(texts), hidden_size]: mean last hidden state over each text's own tokens
    (leading special tokens such as <bos> are fed but not pooled, unless the text is empty)."""
    import torch

    encoded = [lm.encode(t) for t in texts]
    if any(not ids for ids in encoded):
        raise UsageError("cannot embed an empty text with a tokenizer that adds no special tokens")
    out = np.zeros((len(texts), lm.hidden_size), dtype=np.float32)
    skip = len(lm.bos_ids)
    for batch in length_batches([len(ids) for ids in encoded], batch_size):
        state = extend(lm, [encoded[i] for i in batch], hidden=True)
        hidden = state.last_hidden.double()
        for row, i in enumerate(batch):
            own = len(encoded[i]) - skip if len(encoded[i]) > skip else len(encoded[i])
            out[i] = hidden[row, hidden.shape[1] - own:].mean(dim=0).to(torch.float32).cpu().numpy()
    return out
