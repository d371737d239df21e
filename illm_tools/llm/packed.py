"""A state's candidates scored against one copy of its prefix: the candidates packed behind it.

`packed_logprobs` is what `scoring.continuation_logprobs` runs on every model that can take a
custom attention mask. For each state (a row of a `PrefixState`) its K candidates' tokens are laid
one after another in one row behind the cached prefix:

    prefix (cached) | c1[0] c1[1] .. | c2[0] .. | ... | cK[0] ..      (each candidate's last token
                                                                     is not fed: nothing reads it)

A 4D attention mask lets each packed token see the prefix's real columns and its own candidate's
earlier tokens, never another candidate's; position ids restart after the prefix for each
candidate. So every candidate computes what it would behind a copy of the prefix of its own, while
the prefix's KV is held once per state: the memory a state costs is its prefix plus the sum of its
candidates' tokens, not K times the prefix (the repeated form, `repeated_logprobs`, kept for
sliding-window models, whose windows a custom mask would not apply).

The mask is the one part that grows with the square of a state's tokens: [B, 1, Q, L + Q] entries
of the compute dtype (and a [B, Q, Q] bool while it is built). It counts in the batch's token
budget (`illm_tools.llm.budget.mask_bytes`); a batch whose mask alone is over the budget (one state
of many long candidates) scores its candidates in consecutive groups behind the same read-only
cache, each group's mask within the budget (`mask_groups`).

The LM head runs only where a log-prob is read: the decoder's last hidden states at the packed
tokens (padding left out) go through the output layer in slices of `HEAD_ROWS` positions, so the
logits a batch holds at once are bounded whatever its size.

Padding rows of a batch (states with fewer packed tokens than the longest) attend to themselves
only: every query row has a visible key, so no softmax sees only -inf (whose NaN would reach the
real rows through the masked products).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

HEAD_ROWS = 128
"""Positions run through the output layer at a time (a [128, vocabulary] float32 slice: 25 MB at 49k)."""


LEAD = -2
"""`packed_layout`'s owner of a row's lead tokens (seen by every candidate of the row); -1: padding."""


def packed_layout(continuations: Sequence[Sequence[Sequence[int]]],
                  leads: Sequence[Sequence[int]] | None = None) -> tuple[list[list[int]], list[list[int]], list[list[int]]]:
    """Per state row: the fed tokens (its lead tokens, then each candidate but its last token, one
    after another), the owner of each (`LEAD`, or the candidate's index among the flattened
    candidates) and its position after the prefix (lead tokens count on; each candidate's restart
    after the lead)."""
    ids, owner, offset = [], [], []
    r = 0
    for i, cands in enumerate(continuations):
        lead = list(leads[i]) if leads is not None else []
        row_ids, row_owner, row_offset = list(lead), [LEAD] * len(lead), list(range(len(lead)))
        for cand in cands:
            fed = list(cand[:-1])
            row_ids += fed
            row_owner += [r] * len(fed)
            row_offset += [len(lead) + k for k in range(len(fed))]
            r += 1
        ids.append(row_ids)
        owner.append(row_owner)
        offset.append(row_offset)
    return ids, owner, offset


def packed_mask(prefix_mask: Any, owner: Any, dtype: Any) -> Any:
    """[B, 1, Q, L + Q] additive mask (0: seen, the dtype's minimum: hidden) for packed tokens
    behind a prefix whose columns are `prefix_mask` [B, L] (1 real, 0 padding); `owner` [B, Q]
    names each packed token's candidate (`LEAD`: a lead token, seen by all the row's later tokens;
    -1: padding)."""
    import torch

    (b, q), width = owner.shape, prefix_mask.shape[1]
    mask = torch.full((b, 1, q, width + q), torch.finfo(dtype).min, dtype=dtype, device=owner.device)
    mask[:, 0, :, :width].masked_fill_(prefix_mask.bool()[:, None, :], 0)
    own = owner[:, :, None] == owner[:, None, :]  # built in place: the mask and one [B, Q, Q] bool at the peak
    own |= (owner == LEAD)[:, None, :]
    own &= (owner != -1)[:, :, None]
    own.tril_()
    own.diagonal(dim1=1, dim2=2).fill_(True)  # padding rows see themselves
    mask[:, 0, :, width:].masked_fill_(own, 0)
    return mask


def head_logits(lm, hidden: Any) -> Any:
    """float32 logits of the model's output layer over `hidden` [N, H] (with the final soft-capping
    of models that have one)."""
    import torch

    logits = lm.model.get_output_embeddings()(hidden).float()
    cap = getattr(lm.model.config.get_text_config(), "final_logit_softcapping", None)
    return torch.tanh(logits / cap) * cap if cap else logits


def head_logprobs(lm, hidden: Any, targets: Any) -> Any:
    """float32 [N]: log-softmax of the model's output layer over `hidden` [N, H], read at `targets`
    [N], in slices of `HEAD_ROWS`."""
    import torch

    out = []
    for start in range(0, hidden.shape[0], HEAD_ROWS):
        logits = head_logits(lm, hidden[start:start + HEAD_ROWS])
        picked = logits.gather(1, targets[start:start + HEAD_ROWS, None])[:, 0]
        out.append(picked - torch.logsumexp(logits, dim=-1))
    return torch.cat(out) if out else hidden.new_zeros(0, dtype=torch.float32)


@functools.cache
def _read_only_layer():
    """The class of `read_only`'s layers (defined on first use: transformers is imported lazily)."""
    from transformers.cache_utils import DynamicLayer

    class ReadOnlyLayer(DynamicLayer):
        """A cached prefix's keys and values that a forward reads behind its new tokens without
        keeping them: `update` returns prefix + new for this layer's attention and stores nothing,
        so no layer holds a second copy of the prefix once its attention is done."""

        def __init__(self, keys, values):
            super().__init__()
            self.keys, self.values = keys, values
            self.dtype, self.device, self.is_initialized = keys.dtype, keys.device, True

        def update(self, key_states, value_states, *args, **kwargs):
            import torch

            return torch.cat([self.keys, key_states], dim=-2), torch.cat([self.values, value_states], dim=-2)

    return ReadOnlyLayer


def read_only(state) -> Any:
    """`state`'s cache as one a forward reads and never grows (`ReadOnlyLayer`s), or a fork of it
    where a layer is not a plain growing one."""
    import copy

    from transformers.cache_utils import DynamicLayer

    if not all(type(layer) is DynamicLayer and layer.is_initialized for layer in state.cache.layers):
        return state.fork().cache
    cache = copy.copy(state.cache)
    cache.layers = [_read_only_layer()(layer.keys, layer.values) for layer in state.cache.layers]
    return cache


def mask_groups(lm, prefix: int, continuations: Sequence[Sequence[Sequence[int]]],
                leads: Sequence[Sequence[int]] | None = None) -> list[tuple[int, int]]:
    """Ranges of the flattened candidates scored in one packed forward each behind a prefix of
    `prefix` columns: all of them in one when the batch's mask fits `lm.batch_tokens`
    (`budget.mask_tokens`), else consecutive groups whose masks do (one candidate at least each)."""
    from illm_tools.llm.budget import mask_tokens

    rows = len(continuations)
    lead = [len(x) for x in leads] if leads is not None else [0] * rows
    fed = [(i, max(len(c) - 1, 0)) for i, cands in enumerate(continuations) for c in cands]
    totals = list(lead)
    for i, n in fed:
        totals[i] += n
    if lm.batch_tokens is None or mask_tokens(lm.model, rows, max(totals, default=0), prefix) <= lm.batch_tokens:
        return [(0, len(fed))]
    groups, start, held = [], 0, {}  # held: the group's fed tokens per row
    for k, (i, n) in enumerate(fed):
        grown = {**held, i: held.get(i, lead[i]) + n}
        if k > start and mask_tokens(lm.model, rows, max(grown.values()), prefix) > lm.batch_tokens:
            groups.append((start, k))
            start, grown = k, {i: lead[i] + n}
        held = grown
    return [*groups, (start, len(fed))]


def packed_logprobs(lm, state, continuations: Sequence[Sequence[Sequence[int]]], ids: Any, real: Any,
                    grad: bool, leads: Sequence[Sequence[int]] | None = None) -> Any:
    """float32 [N, W] as `scoring.continuation_logprobs` returns it (`ids`, `real`: the flattened
    candidates right-padded [N, W]); `leads`: per row, tokens fed after the prefix and before the
    candidates, seen by all of them (a task's own prompt suffix), whose last logits score the
    candidates' first tokens (without lead tokens: the state's last log-probs). Candidates whose
    mask together is over the budget are scored in groups (`mask_groups`) behind the same cache,
    each group's rows feeding their lead again."""
    import torch

    groups = mask_groups(lm, int(state.attention_mask.shape[1]), continuations, leads)
    if len(groups) == 1:
        return _packed_logprobs(lm, state, continuations, ids, real, grad, leads)
    owner = [i for i, cands in enumerate(continuations) for _ in cands]
    flat = [c for cands in continuations for c in cands]
    parts = []
    for start, end in groups:
        part: list[list] = [[] for _ in continuations]
        for k in range(start, end):
            part[owner[k]].append(flat[k])
        part_leads = [lead if part[i] else [] for i, lead in enumerate(leads)] if leads is not None else None
        parts.append(_packed_logprobs(lm, state, part, ids[start:end], real[start:end], grad, part_leads))
    return torch.cat(parts)


def _packed_logprobs(lm, state, continuations: Sequence[Sequence[Sequence[int]]], ids: Any, real: Any,
                     grad: bool, leads: Sequence[Sequence[int]] | None = None) -> Any:
    """`packed_logprobs` of candidates packed in one forward."""
    import torch

    from illm_tools.llm.forward import cache_kwargs, forward_mode

    fed, owner, offset = packed_layout(continuations, leads)
    width = max(max((len(r) for r in fed), default=0), 1)
    b = len(fed)
    dev = lm.device
    q_ids = torch.full((b, width), lm.pad_id, dtype=torch.long)
    q_owner = torch.full((b, width), -1, dtype=torch.long)
    q_offset = torch.zeros((b, width), dtype=torch.long)
    for i in range(b):
        n = len(fed[i])
        if n:
            q_ids[i, :n] = torch.as_tensor(fed[i])
            q_owner[i, :n] = torch.as_tensor(owner[i])
            q_offset[i, :n] = torch.as_tensor(offset[i])
    q_ids, q_owner, q_offset = q_ids.to(dev), q_owner.to(dev), q_offset.to(dev)
    decoder = lm.model.get_decoder()
    dtype = lm.model.get_input_embeddings().weight.dtype
    mask = packed_mask(state.attention_mask, q_owner, dtype)
    position_ids = state.lengths[:, None] + q_offset
    lead_len = [len(x) for x in leads] if leads is not None else [0] * b
    index = torch.tensor([i for i, cands in enumerate(continuations) for _ in cands], dtype=torch.long, device=dev)
    with forward_mode(grad):
        hidden = decoder(input_ids=q_ids, attention_mask=mask, position_ids=position_ids,
                         **cache_kwargs(read_only(state)), use_cache=True).last_hidden_state
        last = state.last_logprobs
        led = [i for i in range(b) if lead_len[i]]
        if led:  # the candidates' first tokens follow the lead's last token
            at = hidden[torch.tensor(led, device=dev), torch.tensor([lead_len[i] - 1 for i in led], device=dev)]
            last = last.clone()
            last[torch.tensor(led, device=dev)] = torch.log_softmax(head_logits(lm, at), dim=-1)
        first = last[index].gather(1, ids[:, :1])
        if ids.shape[1] == 1:
            return torch.where(real, first, torch.zeros_like(first))
        where = q_owner >= 0
        rows, cols = where.nonzero(as_tuple=True)
        cand = q_owner[rows, cols]
        tok = q_offset[rows, cols] - torch.as_tensor(lead_len, device=dev)[rows]
        targets = ids[cand, tok + 1]
        values = head_logprobs(lm, hidden[rows, cols], targets)
        rest = torch.zeros((ids.shape[0], ids.shape[1] - 1), dtype=torch.float32, device=dev)
        rest = rest.index_put((cand, tok), values)
        logps = torch.cat([first, rest], dim=1)
        return torch.where(real, logps, torch.zeros_like(logps))
