"""The engine's one driver: each state's work planned, batched by tokens, run, decoded and wrapped.

Every use of the transformers engine goes through here: the ranking tasks (`score_candidates`), the
text tasks (`generate`), both tasks of a state over their shared prompt prefix (`score_and_generate`),
the hop backend's prompts of spliced input embeddings (`TransformersBackend.spliced`), and the loss of
`illm distil`, which runs one batch of lessons with autograd on (`run_batch`).

A state's work (`Work`) is a head, run once (tokens, or input embeddings), then any number of scored
branches (per task: a lead of tokens after the head, then its candidates packed behind it,
`scoring.continuation_logprobs`) and at most one greedy continuation (a suffix of tokens after the
head, then up to `max_new_tokens` decoded). The steps:

    plan    `work_tokens`, `work_shape`: its cost in the token budget (`illm_tools.llm.budget`) and the
            geometry of its packed forward (whose mask counts in the budget)
    batch   `budget.token_batches`, states sorted by cost; heads of input embeddings only with heads
            of their own length (they are not padded)
    run     `run_batch`: the batch's heads in one forward, each branch's candidates scored behind them,
            each continuation's suffix prefilled
    decode  `generation.greedy_from` over the prefilled suffixes of up to `decode_batch` states merged
            into one batch (`scoring.merge_states`; on a sliding-window model each batch decodes alone)
    wrap    `CandidateScores` per branch, `Generation` per continuation

Sharing the head is exact (`scoring`'s padding scheme); on a sliding-window model, where padding
between a head and rows of unequal length would shift the window, a caller keeps heads whole (the
backend's `shares_prefix` is False and `score_and_generate` is not used).

Written by hand: transformers' `generate` and pipelines neither share a prompt prefix across tasks,
pack candidates behind one cache, nor batch by a token budget.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from illm_tools.errors import UsageError
from illm_tools.llm.generation import Generation, greedy_from
from illm_tools.llm.loading import LoadedModel
from illm_tools.llm.scoring import (CandidateScores, PrefixState, StatePlan, common_prefix, continuation_logprobs,
                                    extend, merge_states, plan_state, split_logprobs)


@dataclass(frozen=True)
class Work:
    """One state's work for the engine."""

    head: Sequence[int] = ()
    """Tokens run first, once for all its branches and its continuation."""
    embeds: Any = None
    """float [L, d]: input embeddings run as the head instead of tokens (iLLM(hop))."""
    branches: dict[str, StatePlan] = field(default_factory=dict)
    """Per task, what is scored after the head: the plan's `prefix` is the lead (fed after the head,
    not scored), then its candidates (`continuations`, the first `skip` tokens of each fed, not scored)."""
    suffix: Sequence[int] | None = None
    """The continuation's prompt after the head (may be empty); None: nothing decoded."""

    @classmethod
    def scoring(cls, plan: StatePlan, task: str = "action") -> Work:
        """A state's candidates scored after its whole context (`plan_state`), the context its head."""
        return cls(plan.prefix, branches={task: StatePlan([], plan.continuations, plan.skip)})

    @property
    def head_length(self) -> int:
        return len(self.head) if self.embeds is None else int(self.embeds.shape[0])


@dataclass
class Answer:
    """What the engine returns for one `Work`."""

    scores: dict[str, CandidateScores] = field(default_factory=dict)
    generation: Generation | None = None


def branch_tokens(lm: LoadedModel, head: int, plan: StatePlan) -> int:
    """The tokens a branch adds after a head of `head` tokens: its lead and its candidates packed
    behind it (`llm.packed`), or, where candidates are not packed, a copy of head and lead per candidate."""
    if lm.packs_candidates:
        return len(plan.prefix) + sum(max(len(c) - 1, 0) for c in plan.continuations)
    return (head + len(plan.prefix)) * max(len(plan.continuations), 1) - head + sum(len(c) for c in plan.continuations)


def work_tokens(lm: LoadedModel, work: Work, max_new_tokens: int = 0) -> int:
    """The tokens a state's work holds in the engine: its head, its branches, its continuation's
    prompt and the tokens decoded after it."""
    head = work.head_length
    tokens = head + sum(branch_tokens(lm, head, p) for p in work.branches.values())
    return tokens + (len(work.suffix) + max_new_tokens if work.suffix is not None else 0)


def work_shape(work: Work) -> tuple[int, int]:
    """(prefix, fed): the tokens of the state's packed forwards, behind its head: the geometry of its
    candidates' mask (`budget.mask_bytes`)."""
    return work.head_length, sum(len(p.prefix) + sum(max(len(c) - 1, 0) for c in p.continuations)
                                 for p in work.branches.values())


def batches(lm: LoadedModel, costs: Sequence[int], shapes: Sequence[tuple[int, int]],
            batch_size: int) -> list[list[int]]:
    """`budget.token_batches` of states of these costs, each batch's packed mask counted in its
    budget where the model packs candidates."""
    import functools

    from illm_tools.llm.budget import mask_tokens, token_batches

    if not lm.packs_candidates:
        return token_batches(costs, batch_size, lm.batch_tokens)
    return token_batches(costs, batch_size, lm.batch_tokens, shapes, functools.partial(mask_tokens, lm.model))


@dataclass
class BatchRun:
    """`run_batch`'s result for a batch of works."""

    scored: dict[str, tuple[list[int], Any]]
    """Per task: the batch rows that have the branch, and float32 [N, W] per-token log-probs of their
    candidates, flattened in order (`scoring.continuation_logprobs`)."""
    decoding: list[int]
    """The batch rows with a continuation."""
    prompt: PrefixState | None
    """Their continuations' prompts prefilled (a row each), ready for `greedy_from`."""


def run_batch(lm: LoadedModel, works: Sequence[Work], *, grad: bool = False) -> BatchRun:
    """One batch: the heads in one forward (all of them tokens and non-empty, or all input embeddings
    of one length; else each branch and continuation runs its head whole), then each task's branches
    after them and each continuation's suffix prefilled. `grad`: keep autograd on (distillation)."""
    import torch

    if works[0].embeds is not None:
        head = extend(lm, [], embeds=torch.stack([w.embeds for w in works]), grad=grad)
    elif all(w.head for w in works):
        head = extend(lm, [list(w.head) for w in works], grad=grad)
    else:
        head = None
    scored = {}
    for task in dict.fromkeys(t for w in works for t in w.branches):
        rows = [i for i, w in enumerate(works) if task in w.branches]
        plans = [works[i].branches[task] for i in rows]
        if head is not None:
            state, leads = head.select(rows), [p.prefix for p in plans]
        else:
            state, leads = extend(lm, [[*works[i].head, *p.prefix] for i, p in zip(rows, plans)], grad=grad), None
        scored[task] = (rows, continuation_logprobs(lm, state, [p.continuations for p in plans], grad=grad,
                                                    leads=leads))
    decoding = [i for i, w in enumerate(works) if w.suffix is not None]
    prompt = None
    if decoding and head is not None:
        prompt = extend(lm, [list(works[i].suffix) for i in decoding], past=head.select(decoding))
    elif decoding:
        prompt = extend(lm, [[*works[i].head, *works[i].suffix] for i in decoding])
    return BatchRun(scored, decoding, prompt)


def branch_sums(values: Any, plans: Sequence[StatePlan]) -> list:
    """Per plan, a tensor of its candidates' summed log-probs (the skipped tokens left out), from
    `BatchRun.scored`'s values of these plans."""
    import torch

    width = values.shape[1]
    keep = torch.zeros_like(values, dtype=torch.bool)
    r = 0
    for p in plans:
        for cont, skip in zip(p.continuations, p.skip):
            keep[r, skip:min(len(cont), width)] = True
            r += 1
    summed = torch.where(keep, values, torch.zeros_like(values)).sum(1)
    out, r = [], 0
    for p in plans:
        out.append(summed[r:r + len(p.continuations)])
        r += len(p.continuations)
    return out


def wrap_scores(values: Any, plans: Sequence[StatePlan]) -> list[CandidateScores]:
    """Per plan, its candidates' `CandidateScores` (the skipped tokens left out), from
    `BatchRun.scored`'s values of these plans (`scoring.split_logprobs`)."""
    split = split_logprobs(values, [p.continuations for p in plans], [p.skip for p in plans])
    return [CandidateScores.from_logprobs(logprobs) for logprobs in split]


def drive(lm: LoadedModel, works: Sequence[Work], *, batch_size: int = 8, max_new_tokens: int = 0,
          decode_batch: int = 32) -> list[Answer]:
    """Every state's work, in batches of at most `batch_size` states and `lm.batch_tokens` tokens
    (shortest first); the continuations of up to `decode_batch` states, and the budget's tokens, are
    decoded together (decoding is per-step overhead bound: wider steps cost less per state)."""
    if batch_size < 1:
        raise UsageError("batch_size must be at least 1")
    answers = [Answer() for _ in works]
    costs = [work_tokens(lm, w, max_new_tokens) for w in works]
    decode_tokens = [w.head_length + len(w.suffix or ()) + max_new_tokens for w in works]
    pending: list[tuple[list[int], PrefixState]] = []  # (work indices, their prompts) awaiting decoding

    def decode(held: list[tuple[list[int], PrefixState]]) -> None:
        rows = [i for batch, _ in held for i in batch]
        merged = merge_states([state for _, state in held])
        held.clear()  # the merged state is the only holder of the prompts' keys: released into the buffer
        for i, (ids, finished, emb) in zip(rows, greedy_from(lm, merged, max_new_tokens, release=True)):
            answers[i].generation = Generation(lm.tokenizer.decode(ids, skip_special_tokens=True), ids, finished, emb)

    groups: dict[int | None, list[int]] = {}  # heads of input embeddings batch with their own length only
    for i, w in enumerate(works):
        groups.setdefault(None if w.embeds is None else w.head_length, []).append(i)
    for members in groups.values():
        for chosen in batches(lm, [costs[i] for i in members], [work_shape(works[i]) for i in members], batch_size):
            batch = [members[c] for c in chosen]
            run = run_batch(lm, [works[i] for i in batch])
            for task, (rows, values) in run.scored.items():
                for r, scores in zip(rows, wrap_scores(values, [works[batch[r]].branches[task] for r in rows])):
                    answers[batch[r]].scores[task] = scores
            if not run.decoding:
                continue
            pending.append(([batch[r] for r in run.decoding], run.prompt))
            if lm.sliding_window:  # merging would pad between prompts and their windows
                decode(pending)
                continue
            held = [i for b, _ in pending for i in b]
            widest = max(decode_tokens[i] for i in held)
            if len(held) >= decode_batch or (lm.batch_tokens is not None and len(held) * widest >= lm.batch_tokens):
                decode(pending)
    if pending:
        decode(pending)
    return answers


def score_candidates(lm: LoadedModel, contexts: Sequence[str], candidates: Sequence[Sequence[str]], *,
                     batch_size: int = 8) -> list[CandidateScores]:
    """log P(candidate | context) for each state's candidates (joint tokenisation, KV reuse)."""
    if len(contexts) != len(candidates):
        raise UsageError(f"{len(contexts)} contexts but {len(candidates)} candidate lists")
    plans = [plan_state(lm, ctx, cands) for ctx, cands in zip(contexts, candidates)]
    works = [Work.scoring(p) for p in plans]
    return [a.scores["action"] for a in drive(lm, works, batch_size=batch_size)]


def generate(lm: LoadedModel, prompts: Sequence[str], *, max_new_tokens: int = 64,
             batch_size: int = 8) -> list[Generation]:
    """Greedy (temperature 0) continuations of `prompts`, in order, with summary embeddings; each batch
    decoded as soon as it is prefilled."""
    if max_new_tokens < 1:
        raise UsageError("max_new_tokens must be at least 1")
    encoded = [lm.encode(p) for p in prompts]
    if any(not ids for ids in encoded):
        raise UsageError("cannot generate from an empty prompt")
    works = [Work(ids, suffix=()) for ids in encoded]
    return [a.generation for a in drive(lm, works, batch_size=batch_size, max_new_tokens=max_new_tokens,
                                        decode_batch=1)]


def score_and_generate(lm: LoadedModel, contexts: Sequence[str], candidates: Sequence[Sequence[str]],
                       prompts: Sequence[str], *, max_new_tokens: int = 64, batch_size: int = 8,
                       decode_batch: int = 32) -> tuple[list[CandidateScores], list[Generation]]:
    """For each state i: log P(candidates[i] | contexts[i]) and the greedy continuation of prompts[i],
    the tokens the two prompts share run once (the `shared` template layout's task line and history).
    Results equal `score_candidates` and `generate` on the full prompts (checked in tests)."""
    plans = [plan_state(lm, c, cands) for c, cands in zip(contexts, candidates)]
    summary_ids = [lm.encode(p) for p in prompts]
    works = []
    for plan, ids in zip(plans, summary_ids):
        # keep one token of each summary prompt out of the head: its logits start the decoding
        shared = min(common_prefix(plan.prefix, ids), len(ids) - 1)
        works.append(Work(plan.prefix[:shared], suffix=ids[shared:],
                          branches={"action": StatePlan(plan.prefix[shared:], plan.continuations, plan.skip)}))
    answers = drive(lm, works, batch_size=batch_size, max_new_tokens=max_new_tokens, decode_batch=decode_batch)
    return [a.scores["action"] for a in answers], [a.generation for a in answers]
