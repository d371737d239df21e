"""Scoring candidate continuations: the one code path for log P(candidate | context).

Owns `PrefixState` (a KV cache over a batch of token rows, left-padded, with the log-probs of the
next token), the steps built on it, and a state's tokens (`plan_state`):

    extend(lm, rows, past=None)          run new tokens, optionally continuing a cached prefix
    continuation_logprobs(lm, state, ...) per-token log-probs of K token continuations per row (a tensor)
    score_continuations(lm, state, ...)  the same as lists, the skipped tokens left out
    plan_state(lm, context, candidates)  tokenise a context and its candidates together

The engine's driver (`illm_tools.llm.driver`) plans, batches, runs, decodes and wraps with these for
every caller. `extend(..., grad=True)` and `continuation_logprobs(..., grad=True)` run the same
computation with autograd on: `illm distil` trains a student through this path, so the scores it
learns are the scores the annotator computes.

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
A state's candidates are packed one after another behind one copy of its context cache, each
seeing the context and its own earlier tokens through a 4D mask, positions restarting after the
context (`illm_tools.llm.packed`): a state holds its prompt's KV once, not once per candidate.
Sliding-window models, whose windows such a mask would not apply, run each candidate behind a
copy of the cache (`repeated_logprobs`, right-padded: trailing padding is never attended by real
tokens). Batches of states are bounded by a token budget (`illm_tools.llm.budget`).

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
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from illm_tools.errors import UsageError
from illm_tools.llm.forward import cache_kwargs, forward_mode, returned_cache
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
        if len({len(r) for r in rows}) > 1 and lm.sliding_window:
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
    with forward_mode(grad):
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
                        skip: Sequence[Sequence[int]] | None = None,
                        leads: Sequence[Sequence[int]] | None = None) -> list[list[list[float]]]:
    """For each row of `state`, the per-token log-probs of each of its token continuations.

    `continuations[i]` lists row i's candidates (any number). `skip[i][k]` leading tokens of a
    candidate are fed but not scored (context tokens after a straddling boundary). `leads[i]`:
    tokens of row i's context after `state` (a task's own prompt suffix after a shared prefix),
    fed with the candidates where they are packed (no copy of the state's cache for them). `state`
    is left untouched, so the same state can score further candidates.
    """
    if not any(continuations):
        if len(continuations) != state.batch_size:
            raise ValueError(f"{len(continuations)} candidate lists for {state.batch_size} rows")
        return [[] for _ in continuations]
    return split_logprobs(continuation_logprobs(lm, state, continuations, leads=leads), continuations, skip)


def split_logprobs(values: Any, continuations: Sequence[Sequence[Sequence[int]]],
                   skip: Sequence[Sequence[int]] | None = None) -> list[list[list[float]]]:
    """`continuation_logprobs`' [N, W] tensor as lists: per row, per candidate, the log-probs of its
    tokens after the first `skip[i][k]` (fed, not scored)."""
    flat = [c for cands in continuations for c in cands]
    skips = [s for row in (skip or [[0] * len(c) for c in continuations]) for s in row]
    per_row = [vals[s:len(c)] for vals, c, s in zip(values.tolist(), flat, skips)]
    result, start = [], 0
    for cands in continuations:
        result.append(per_row[start:start + len(cands)])
        start += len(cands)
    return result


def continuation_logprobs(lm: LoadedModel, state: PrefixState, continuations: Sequence[Sequence[Sequence[int]]], *,
                          grad: bool = False, leads: Sequence[Sequence[int]] | None = None) -> Any:
    """float32 [N, W]: the log-prob of each token of each continuation after its row of `state`
    (rows' continuations flattened in order, N in all, right-padded to the longest, W; positions
    past a continuation's end hold 0). The first token's log-prob is the state's last logits';
    tokens 2.. come from one forward of each row's continuations packed behind its cache
    (`illm_tools.llm.packed`), or, on a sliding-window model, behind a copy of the row's cache per
    continuation (`repeated_logprobs`). `leads`: per row, context tokens after `state` fed first
    (packed with the candidates, else run through `extend`). `grad`: keep autograd on (training)."""
    import torch

    if len(continuations) != state.batch_size:
        raise ValueError(f"{len(continuations)} candidate lists for {state.batch_size} rows")
    if leads is not None and any(leads) and not lm.packs_candidates:
        state, leads = extend(lm, leads, past=state, grad=grad), None
    if leads is not None and not any(leads):
        leads = None
    flat = [list(c) for cands in continuations for c in cands]
    index = torch.tensor([i for i, cands in enumerate(continuations) for _ in cands], device=lm.device)
    width = max(max(len(c) for c in flat), 1)
    ids = torch.full((len(flat), width), lm.pad_id, dtype=torch.long)
    real = torch.zeros((len(flat), width), dtype=torch.bool)
    for r, cand in enumerate(flat):
        ids[r, :len(cand)] = torch.as_tensor(cand, dtype=torch.long)
        real[r, :len(cand)] = True
    ids, real = ids.to(lm.device), real.to(lm.device)
    if lm.packs_candidates and (width > 1 or leads is not None):
        from illm_tools.llm.packed import packed_logprobs

        return packed_logprobs(lm, state, continuations, ids, real, grad, leads)
    first = state.last_logprobs[index].gather(1, ids[:, :1])
    if width == 1:
        return torch.where(real, first, torch.zeros_like(first))
    return repeated_logprobs(lm, state, index, ids, real, first, grad)


def repeated_logprobs(lm: LoadedModel, state: PrefixState, index: Any, ids: Any, real: Any, first: Any,
                      grad: bool) -> Any:
    """`continuation_logprobs` with the row's cache repeated once per continuation (K copies of the
    prefix's KV): the path of sliding-window models, and the reference the packed one is tested against."""
    import torch

    width = ids.shape[1]
    rows = state.select(index)
    inputs = ids[:, :-1]
    position_ids = rows.lengths[:, None] + torch.arange(width - 1, device=lm.device)
    with forward_mode(grad):
        out = lm.model(input_ids=inputs, attention_mask=torch.cat([rows.attention_mask, real[:, :-1].long()], 1),
                       position_ids=position_ids, **cache_kwargs(rows.cache), use_cache=True)
        logits = out.logits.float()
        rest = logits.gather(2, ids[:, 1:, None])[..., 0] - torch.logsumexp(logits, dim=-1)
        logps = torch.cat([first, rest], dim=1)
        return torch.where(real, logps, torch.zeros_like(logps))


@dataclass(frozen=True)
class StatePlan:
    """One state's scoring, tokenised (`plan_state`); the engine's driver (`illm_tools.llm.driver`)
    also holds a task's branch after a shared head in one, its `prefix` then the lead after the head."""

    prefix: list[int]
    """The context's tokens all candidates share (up to the boundary a candidate's first token may merge into)."""
    continuations: list[list[int]]
    """Each candidate's tokens after the prefix."""
    skip: list[int]
    """Per candidate, the leading tokens of its continuation that belong to the context (not scored)."""


def common_prefix(a: Sequence[int], b: Sequence[int]) -> int:
    n = 0
    for x, y in zip(a, b):
        if x != y:
            break
        n += 1
    return n


def plan_state(lm: LoadedModel, context: str, candidates: Sequence[str]) -> StatePlan:
    """Tokenise a context and its candidates together and split them at the boundary."""
    context_ids = lm.encode(context)
    joint = [lm.encode(context + cand) for cand in candidates]
    owns = [common_prefix(context_ids, ids) for ids in joint]
    shared = min(owns, default=len(context_ids))
    if shared < len(context_ids):
        log.debug("context and candidate share a token at the boundary; scoring from token %d", shared)
    return StatePlan(context_ids[:shared], [ids[shared:] for ids in joint], [o - shared for o in owns])
