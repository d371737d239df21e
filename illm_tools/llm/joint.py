"""Both language tasks of a state in one pass over their shared prompt prefix.

With the `shared` template layout the action and summary prompts of a state start with the same
text (task line and history, most of the tokens). Here that prefix is run once per state; the
action prompt's own suffix and its candidates, and the summary prompt's suffix and its greedy
continuation, both continue from it. Results equal scoring and generating from the full prompts
(checked in tests); on sliding-window models (padding between prefix and suffix would shift the
window) callers use the separate paths instead.
"""

from __future__ import annotations

from collections.abc import Sequence

from illm_tools.llm.generation import Generation, greedy_from
from illm_tools.llm.loading import LoadedModel
from illm_tools.llm.scoring import (CandidateScores, common_prefix, extend, merge_states, packed_batches, plan_shape,
                                    plan_state, plan_tokens, score_plans)


def score_and_generate(lm: LoadedModel, contexts: Sequence[str], candidates: Sequence[Sequence[str]],
                       prompts: Sequence[str], *, max_new_tokens: int = 64, batch_size: int = 8,
                       decode_batch: int = 32) -> tuple[list[CandidateScores], list[Generation]]:
    """For each state i: log P(candidates[i] | contexts[i]) and the greedy continuation of
    prompts[i], computing the tokens the two prompts share once. Prompts are prefilled in
    length-sorted batches of at most `batch_size` states and `lm.batch_tokens` tokens (a state's:
    its action prompt with its packed candidates, its summary prompt's own tokens and the summary;
    the candidates' mask counted too);
    the summaries of up to `decode_batch` states, and the budget's tokens, are then decoded
    together (decoding is per-step overhead bound: wider steps cost less per state)."""
    plans = [plan_state(lm, c, cands) for c, cands in zip(contexts, candidates)]
    summary_ids = [lm.encode(p) for p in prompts]
    # keep one token of each summary prompt out of the prefix: its logits start the decoding
    shared = [min(common_prefix(p.prefix, s), len(s) - 1) for p, s in zip(plans, summary_ids)]
    scores: list[CandidateScores | None] = [None] * len(plans)
    gens: list[Generation | None] = [None] * len(plans)
    pending: list[tuple[list[int], object]] = []  # (state indices, summary state) awaiting decoding
    decode_tokens = [len(s) + max_new_tokens for s in summary_ids]
    budget = lm.batch_tokens

    def decode() -> None:
        rows = [i for batch, _ in pending for i in batch]
        merged = merge_states([state for _, state in pending])
        pending.clear()  # the merged state is the only holder of the prompts' keys: released into the buffer
        decoded = greedy_from(lm, merged, max_new_tokens, release=True)
        for i, (ids, finished, emb) in zip(rows, decoded):
            gens[i] = Generation(lm.tokenizer.decode(ids, skip_special_tokens=True), ids, finished, emb)

    costs = [plan_tokens(lm, p) + len(s) - shared_n + max_new_tokens
             for p, s, shared_n in zip(plans, summary_ids, shared)]
    shapes = [plan_shape(p, cached=n) for p, n in zip(plans, shared)]  # the action prompt's end fed with its candidates
    for batch in packed_batches(lm, costs, shapes, batch_size):
        prefix = extend(lm, [plans[i].prefix[:shared[i]] for i in batch])
        leads = [plans[i].prefix[shared[i]:] for i in batch]  # the action prompt's own end
        for i, scored in zip(batch, score_plans(lm, prefix, [plans[i] for i in batch], leads=leads)):
            scores[i] = scored
        pending.append((batch, extend(lm, [summary_ids[i][shared[i]:] for i in batch], past=prefix)))
        held = [i for b, _ in pending for i in b]
        if len(held) >= decode_batch or (budget is not None and len(held) * max(decode_tokens[i] for i in held) >= budget):
            decode()
    if pending:
        decode()
    return scores, gens  # type: ignore[return-value]
