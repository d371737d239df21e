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
from illm_tools.llm.scoring import (CandidateScores, common_prefix, extend, has_sliding_window, length_batches,
                                    merge_states, plan_state, score_continuations)


def can_share_prefix(lm: LoadedModel) -> bool:
    return not has_sliding_window(lm)


def score_and_generate(lm: LoadedModel, contexts: Sequence[str], candidates: Sequence[Sequence[str]],
                       prompts: Sequence[str], *, max_new_tokens: int = 64, batch_size: int = 8,
                       decode_batch: int = 32) -> tuple[list[CandidateScores], list[Generation]]:
    """For each state i: log P(candidates[i] | contexts[i]) and the greedy continuation of
    prompts[i], computing the tokens the two prompts share once. Prompts are prefilled in
    length-sorted batches of `batch_size`; the summaries of up to `decode_batch` states are then
    decoded together (decoding is per-step overhead bound: wider steps cost less per state)."""
    plans = [plan_state(lm, c, cands) for c, cands in zip(contexts, candidates)]
    summary_ids = [lm.encode(p) for p in prompts]
    # keep one token of each summary prompt out of the prefix: its logits start the decoding
    shared = [min(common_prefix(p.prefix, s), len(s) - 1) for p, s in zip(plans, summary_ids)]
    scores: list[CandidateScores | None] = [None] * len(plans)
    gens: list[Generation | None] = [None] * len(plans)
    pending: list[tuple[list[int], object]] = []  # (state indices, summary state) awaiting decoding

    def decode() -> None:
        rows = [i for batch, _ in pending for i in batch]
        decoded = greedy_from(lm, merge_states([state for _, state in pending]), max_new_tokens)
        for i, (ids, finished, emb) in zip(rows, decoded):
            gens[i] = Generation(lm.tokenizer.decode(ids, skip_special_tokens=True), ids, finished, emb)
        pending.clear()

    for batch in length_batches([len(p.prefix) for p in plans], batch_size):
        prefix = extend(lm, [plans[i].prefix[:shared[i]] for i in batch])
        action = extend(lm, [plans[i].prefix[shared[i]:] for i in batch], past=prefix)
        logps = score_continuations(lm, action, [plans[i].continuations for i in batch],
                                    [plans[i].skip for i in batch])
        for i, lp in zip(batch, logps):
            scores[i] = CandidateScores.from_logprobs(lp)
        pending.append((batch, extend(lm, [summary_ids[i][shared[i]:] for i in batch], past=prefix)))
        if sum(len(b) for b, _ in pending) >= decode_batch:
            decode()
    if pending:
        decode()
    return scores, gens  # type: ignore[return-value]
