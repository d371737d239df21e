"""Scoring candidate continuations: the one code path for log P(candidate | context).

Owns `PrefixState` (a KV cache over a batch of token rows, left-padded, with the log-probs of the
next token) and the three steps built on it:

    extend(lm, rows, past=None)          run new tokens, optionally continuing a cached prefix
    score_continuations(lm, state, ...)  per-token log-probs of K token continuations per row
    score_candidates(lm, contexts, ...)  tokenise, batch states sorted by length, score

`extend(..., grad=True)` and `continuation_logprobs` (the tensor under `score_continuations`) run
the same computation with autograd on: `illm distil` trains a student through this path, so the
scores it learns are the scores the annotator computes.

Padding scheme. Each new segment is left-padded so that every row's last real token sits in the
last column: its logits give the first candidate token's log-prob for all rows at once. Padding
columns are masked out in `attention_mask`, and position ids count real tokens only, so a
padded row computes what it would alone (up to float rounding). A cached prefix of one row can
be continued by several rows (`extend(lm, rows, past=prefix)`): the padding then sits between
the prefix and each row's new tokens, which the mask and position ids make invisible. This is
how a prompt head shared by both language tasks is computed once.
Left padding is also exact for sliding-window models (Gemma 3): the pads sit before every real
token, so each window holds the same real tokens; padding between a prefix and new rows would
not, so `extend` refuses rows of unequal length after a prefix on such models.
Candidates are right-padded behind the context cache (repeated K times per state); trailing
padding is never attended by real tokens, so it needs no care beyond ignoring its outputs.

Tokenisation boundary. Context and candidate are tokenised together: ids(context + candidate).
When ids(context) is a prefix of that (the usual case, candidates start with a space), the
candidate's tokens are the ones after it. When a token straddles the boundary (e.g. a context
ending in a space), the candidate's tokens are those after the longest common prefix of
ids(context) and ids(context + candidate); the shared cache then stops at the shortest such
prefix over the state's candidates and the context tokens fed after it are not scored.
So the sum is always log P(candidate's tokens | the tokens before them), joint tokenisation.
"""

from __future__ import annotations

import copy
import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from illm_tools.errors import UsageError
from illm_tools.llm.loading import LoadedModel

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CandidateScores:
    """Scores of one state's candidates, in the order given."""

    token_logprobs: list[list[float]]
    """Per candidate, the log-prob of each of its tokens (natural log)."""
    token_counts: list[int]
    """Per candidate, how many tokens it has (joint tokenisation with its context)."""
    sums: list[float]
    """Per candidate, the summed log-prob: log P(candidate | context)."""

    @classmethod
    def from_logprobs(cls, token_logprobs: list[list[float]]) -> CandidateScores:
        return cls(token_logprobs, [len(t) for t in token_logprobs], [float(sum(t)) for t in token_logprobs])

    @property
    def best(self) -> int:
        """Index of the candidate with the highest summed log-prob (first on ties)."""
        return max(range(len(self.sums)), key=self.sums.__getitem__)


@dataclass
class PrefixState:
    """A KV cache over a batch of token rows; row i's next position id is `lengths[i]`."""

    cache: Any
    """transformers Cache; never mutated once built (extend and select work on forks)."""
    attention_mask: Any
    """[B, L] long: 1 at real tokens, 0 at padding."""
    lengths: Any
    """[B] long: real tokens per row."""
    last_logprobs: Any
    """[B, V] float32: log-softmax of the logits after each row's last real token."""
    last_hidden: Any = None
    """[B, L_new, H]: last hidden layer over the latest extend's columns, when asked for."""

    @property
    def batch_size(self) -> int:
        return int(self.lengths.shape[0])

    def fork(self) -> PrefixState:
        """A copy that can be extended without touching this state (tensors are shared, not
        copied: cache layers replace their tensors on update rather than writing into them)."""
        cache = copy.copy(self.cache)
        cache.layers = [copy.copy(layer) for layer in self.cache.layers]
        return PrefixState(cache, self.attention_mask, self.lengths, self.last_logprobs)

    def select(self, index: Sequence[int] | Any) -> PrefixState:
        """Rows `index` (repeats allowed) as a new state sharing nothing mutable with this one."""
        import torch

        index = torch.as_tensor(index, dtype=torch.long, device=self.lengths.device)
        state = self.fork()
        if index.tolist() == list(range(self.batch_size)):
            return state
        state.cache.batch_select_indices(index)
        return PrefixState(state.cache, self.attention_mask[index], self.lengths[index], self.last_logprobs[index])


def merge_states(states: Sequence[PrefixState]) -> PrefixState:
    """One state holding the rows of several (e.g. prompt batches prefilled apart, to be decoded
    together): shorter caches are left-padded with masked columns, which shift no position ids
    (those come from `lengths`). Not for sliding-window models (padding would shift the window)."""
    import copy

    import torch
    import torch.nn.functional as F

    if len(states) == 1:
        return states[0]
    width = max(s.attention_mask.shape[1] for s in states)
    pads = [width - s.attention_mask.shape[1] for s in states]
    cache = copy.copy(states[0].cache)
    cache.layers = []
    for i, layer in enumerate(states[0].cache.layers):
        merged = copy.copy(layer)
        merged.keys = torch.cat([F.pad(s.cache.layers[i].keys, (0, 0, p, 0)) for s, p in zip(states, pads)])
        merged.values = torch.cat([F.pad(s.cache.layers[i].values, (0, 0, p, 0)) for s, p in zip(states, pads)])
        cache.layers.append(merged)
    mask = torch.cat([F.pad(s.attention_mask, (p, 0)) for s, p in zip(states, pads)])
    return PrefixState(cache, mask, torch.cat([s.lengths for s in states]),
                       torch.cat([s.last_logprobs for s in states]))


def _left_pad(rows: Sequence[Sequence[int]], pad_id: int, device: Any) -> tuple[Any, Any]:
    import torch

    width = max(len(r) for r in rows)
    ids = torch.full((len(rows), width), pad_id, dtype=torch.long)
    mask = torch.zeros((len(rows), width), dtype=torch.long)
    for i, row in enumerate(rows):
        if row:
            ids[i, width - len(row):] = torch.as_tensor(row)
            mask[i, width - len(row):] = 1
    return ids.to(device), mask.to(device)


def has_sliding_window(lm: LoadedModel) -> bool:
    """Whether some attention layer sees only a window of recent columns (e.g. Gemma 3)."""
    config = lm.model.config.get_text_config()
    types = getattr(config, "layer_types", None)
    if types is not None:
        return "sliding_attention" in types
    return getattr(config, "sliding_window", None) is not None


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


def _forward_mode(grad: bool):
    """autograd on (training: `illm distil`) or inference mode (annotation, probing)."""
    import contextlib

    import torch

    return contextlib.nullcontext() if grad else torch.inference_mode()


def extend(lm: LoadedModel, rows: Sequence[Sequence[int]], past: PrefixState | None = None, *,
           hidden: bool = False, embeds: Any = None, grad: bool = False) -> PrefixState:
    """Run `rows` (one token list per batch row, left-padded here) after `past` and return the
    new state; `past` (of batch 1 or len(rows)) is left untouched and can be extended again.
    `embeds` (float [B, L, d], every row L real positions) runs input embeddings instead of tokens
    (iLLM(hop)'s translated observations; `rows` is then ignored). `grad`: keep autograd on."""
    import torch
    from transformers import DynamicCache

    if embeds is not None:
        rows = [[lm.pad_id] * int(embeds.shape[1])] * int(embeds.shape[0])  # the shape; ids unused
    if past is not None:
        if past.batch_size not in (1, len(rows)):
            raise ValueError(f"past has {past.batch_size} rows, got {len(rows)}")
        if len({len(r) for r in rows}) > 1 and has_sliding_window(lm):
            raise ValueError("rows continuing a cached prefix on a sliding-window model must have equal "
                             "lengths (padding between prefix and rows would shift the window)")
        past = past.select([0] * len(rows) if past.batch_size == 1 else range(len(rows)))
        if not any(rows):
            return past
    elif any(len(r) == 0 for r in rows):
        raise UsageError("cannot score after an empty context: give each context at least one token")
    ids, mask = _left_pad(rows, lm.pad_id, lm.device)
    before = past.lengths if past is not None else torch.zeros(len(rows), dtype=torch.long, device=lm.device)
    position_ids = (before[:, None] + mask.cumsum(1) - 1).clamp(min=0)
    full_mask = mask if past is None else torch.cat([past.attention_mask, mask], dim=1)
    cache = past.cache if past is not None else DynamicCache(config=lm.model.config)
    # the last column's logits only, asked for by index: `logits_to_keep=1` slices a non-contiguous
    # view, which the head then multiplies as a batched matmul over a copy of its weight per row
    # (≈ 100x slower on CPU for a 49k vocabulary); the index gathers a contiguous [B, 1, H] first
    last = torch.tensor([ids.shape[1] - 1], device=lm.device)
    inputs = {"input_ids": ids} if embeds is None else {
        "inputs_embeds": embeds.to(device=lm.device, dtype=lm.model.get_input_embeddings().weight.dtype)}
    with _forward_mode(grad):
        out = lm.model(**inputs, attention_mask=full_mask, position_ids=position_ids,
                       **cache_kwargs(cache), use_cache=True, logits_to_keep=last,
                       output_hidden_states=hidden)
    logprobs = torch.log_softmax(out.logits[:, -1].float(), dim=-1)
    n_new = mask.sum(1)
    if past is not None and bool((n_new == 0).any()):  # rows with nothing new keep their log-probs
        logprobs = torch.where((n_new == 0)[:, None], past.last_logprobs, logprobs)
    return PrefixState(returned_cache(out), full_mask, before + n_new, logprobs,
                       out.hidden_states[-1] if hidden else None)


def score_continuations(lm: LoadedModel, state: PrefixState, continuations: Sequence[Sequence[Sequence[int]]],
                        skip: Sequence[Sequence[int]] | None = None) -> list[list[list[float]]]:
    """For each row of `state`, the per-token log-probs of each of its token continuations.

    `continuations[i]` lists row i's candidates (any number). `skip[i][k]` leading tokens of a
    candidate are fed but not scored (context tokens after a straddling boundary). `state` is
    left untouched, so the same state can score further candidates.
    """
    flat = [list(c) for cands in continuations for c in cands]
    skips = [s for row in (skip or [[0] * len(c) for c in continuations]) for s in row]
    if not flat:
        if len(continuations) != state.batch_size:
            raise ValueError(f"{len(continuations)} candidate lists for {state.batch_size} rows")
        return [[] for _ in continuations]
    values = continuation_logprobs(lm, state, continuations).tolist()
    per_row = [vals[s:len(c)] for vals, c, s in zip(values, flat, skips)]
    result, start = [], 0
    for cands in continuations:
        result.append(per_row[start:start + len(cands)])
        start += len(cands)
    return result


def continuation_logprobs(lm: LoadedModel, state: PrefixState, continuations: Sequence[Sequence[Sequence[int]]], *,
                          grad: bool = False) -> Any:
    """float32 [N, W]: the log-prob of each token of each continuation after its row of `state`
    (rows' continuations flattened in order, N in all, right-padded to the longest, W; positions
    past a continuation's end hold 0). The first token's log-prob is the state's last logits';
    tokens 2.. come from one forward of the continuations behind the row's cache, repeated once per
    continuation. `grad`: keep autograd on (training)."""
    import torch

    if len(continuations) != state.batch_size:
        raise ValueError(f"{len(continuations)} candidate lists for {state.batch_size} rows")
    flat = [list(c) for cands in continuations for c in cands]
    index = torch.tensor([i for i, cands in enumerate(continuations) for _ in cands], device=lm.device)
    width = max(max(len(c) for c in flat), 1)
    ids = torch.full((len(flat), width), lm.pad_id, dtype=torch.long)
    real = torch.zeros((len(flat), width), dtype=torch.bool)
    for r, cand in enumerate(flat):
        ids[r, :len(cand)] = torch.as_tensor(cand, dtype=torch.long)
        real[r, :len(cand)] = True
    ids, real = ids.to(lm.device), real.to(lm.device)
    first = state.last_logprobs[index].gather(1, ids[:, :1])
    if width == 1:
        return torch.where(real, first, torch.zeros_like(first))
    rows = state.select(index)
    inputs = ids[:, :-1]
    position_ids = rows.lengths[:, None] + torch.arange(width - 1, device=lm.device)
    with _forward_mode(grad):
        out = lm.model(input_ids=inputs, attention_mask=torch.cat([rows.attention_mask, real[:, :-1].long()], 1),
                       position_ids=position_ids, **cache_kwargs(rows.cache), use_cache=True)
        logits = out.logits.float()
        rest = logits.gather(2, ids[:, 1:, None])[..., 0] - torch.logsumexp(logits, dim=-1)
        logps = torch.cat([first, rest], dim=1)
        return torch.where(real, logps, torch.zeros_like(logps))


@dataclass(frozen=True)
class _Plan:
    prefix: list[int]
    continuations: list[list[int]]
    skip: list[int]


def common_prefix(a: Sequence[int], b: Sequence[int]) -> int:
    n = 0
    for x, y in zip(a, b):
        if x != y:
            break
        n += 1
    return n


def plan_state(lm: LoadedModel, context: str, candidates: Sequence[str]) -> _Plan:
    """Tokenise a context and its candidates together and split them at the boundary."""
    context_ids = lm.encode(context)
    joint = [lm.encode(context + cand) for cand in candidates]
    owns = [common_prefix(context_ids, ids) for ids in joint]
    shared = min(owns, default=len(context_ids))
    if shared < len(context_ids):
        log.debug("context and candidate share a token at the boundary; scoring from token %d", shared)
    return _Plan(context_ids[:shared], [ids[shared:] for ids in joint], [o - shared for o in owns])


def length_batches(lengths: Sequence[int], batch_size: int) -> list[list[int]]:
    """Indices grouped into batches of similar length (sorted, so padding stays small)."""
    if batch_size < 1:
        raise UsageError("batch_size must be at least 1")
    order = sorted(range(len(lengths)), key=lengths.__getitem__)
    return [order[i:i + batch_size] for i in range(0, len(order), batch_size)]


def score_candidates(lm: LoadedModel, contexts: Sequence[str], candidates: Sequence[Sequence[str]], *,
                     batch_size: int = 8) -> list[CandidateScores]:
    """log P(candidate | context) for each state's candidates (joint tokenisation, KV reuse)."""
    if len(contexts) != len(candidates):
        raise UsageError(f"{len(contexts)} contexts but {len(candidates)} candidate lists")
    plans = [plan_state(lm, ctx, cands) for ctx, cands in zip(contexts, candidates)]
    results: list[CandidateScores | None] = [None] * len(plans)
    for batch in length_batches([len(p.prefix) for p in plans], batch_size):
        state = extend(lm, [plans[i].prefix for i in batch])
        scored = score_continuations(lm, state, [plans[i].continuations for i in batch],
                                     [plans[i].skip for i in batch])
        for i, logprobs in zip(batch, scored):
            results[i] = CandidateScores.from_logprobs(logprobs)
    return results  # type: ignore[return-value]
