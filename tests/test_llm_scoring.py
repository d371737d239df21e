"""The one scoring path against a plain per-candidate forward: tiny models (Llama without and with
<bos>, Gemma 3 with a sliding window), the tokenisation boundary, batching, prefix reuse; and
(slow) the embedded SmolLM2 in float32 and bfloat16."""

from __future__ import annotations

import pytest
from conftest import ACTIONS, babyai_context, plain_scores

from illm_tools.errors import UsageError
from illm_tools.llm.driver import score_candidates
from illm_tools.llm.scoring import CandidateScores, extend, plan_state, score_continuations

CANDS = [" " + a for a in ACTIONS]


def _max_diff(got: list[list[float]], want: list[list[float]]) -> float:
    assert [len(g) for g in got] == [len(w) for w in want]
    return max(abs(a - b) for g, w in zip(got, want) for a, b in zip(g, w))


@pytest.mark.parametrize("fixture", ["tiny_lm", "tiny_lm_bos", "tiny_lm_gpt2", "tiny_lm_sliding"])
def test_matches_plain_forward_per_candidate(fixture, request):
    lm = request.getfixturevalue(fixture)
    contexts = [babyai_context(i) for i in range(5)]  # three lengths, so batches mix padding
    results = score_candidates(lm, contexts, [CANDS] * 5, batch_size=3)
    for context, scores in zip(contexts, results):
        want = plain_scores(lm, context, CANDS)
        assert _max_diff(scores.token_logprobs, want) < 1e-4
        assert scores.best == max(range(len(want)), key=lambda k: sum(want[k]))
        assert scores.token_counts == [len(w) for w in want]
        assert scores.sums == pytest.approx([sum(w) for w in want], abs=1e-4)


def test_batch_size_does_not_change_scores(tiny_lm):
    contexts = [babyai_context(i) for i in range(6)]
    one = score_candidates(tiny_lm, contexts, [CANDS] * 6, batch_size=1)
    many = score_candidates(tiny_lm, contexts, [CANDS] * 6, batch_size=6)
    for a, b in zip(one, many):
        assert _max_diff(a.token_logprobs, b.token_logprobs) < 1e-5


def test_boundary_token_straddling_context_and_candidate(tiny_lm):
    context = "Valid actions: go forward, pick up. Action: "  # trailing space merges into the candidate
    plan = plan_state(tiny_lm, context, ACTIONS)
    assert len(plan.prefix) < len(tiny_lm.encode(context))  # the shared cache stops before the space
    (scores,) = score_candidates(tiny_lm, [context], [ACTIONS])
    assert _max_diff(scores.token_logprobs, plain_scores(tiny_lm, context, ACTIONS)) < 1e-4


def test_clean_boundary_keeps_whole_context(tiny_lm):
    context = babyai_context(0)
    plan = plan_state(tiny_lm, context, CANDS)
    assert plan.prefix == tiny_lm.encode(context)
    assert plan.skip == [0] * len(CANDS)


def test_varied_candidate_counts_and_empty_candidate(tiny_lm):
    contexts = [babyai_context(0), babyai_context(1), babyai_context(2)]
    candidates = [[" go forward"], CANDS, [" drop", ""]]
    results = score_candidates(tiny_lm, contexts, candidates, batch_size=3)
    assert [len(r.sums) for r in results] == [1, 6, 2]
    assert results[2].token_counts[1] == 0 and results[2].sums[1] == 0.0
    for context, cands, scores in zip(contexts, candidates, results):
        assert _max_diff(scores.token_logprobs, plain_scores(tiny_lm, context, cands)) < 1e-4


@pytest.mark.parametrize("fixture", ["tiny_lm", "tiny_lm_sliding"])
def test_shared_prefix_cache_is_reusable(fixture, request):
    lm = request.getfixturevalue(fixture)
    tok = lm.tokenizer
    head = lm.encode("You are an expert player playing BabyAI. Valid actions: go forward, drop")
    tails = [tok(t, add_special_tokens=False)["input_ids"] for t in
             ["\nYou see: a wall.\nAction:", "\nYou see: a red ball 2 steps left.\nAction:"]]
    tails[1] = tails[1][:len(tails[0])] if fixture == "tiny_lm_sliding" else tails[1]
    cands = [[tok(c, add_special_tokens=False)["input_ids"] for c in CANDS]] * 2
    prefix = extend(lm, [head])
    first = score_continuations(lm, extend(lm, tails, past=prefix), cands)
    again = score_continuations(lm, extend(lm, tails, past=prefix), cands)  # prefix untouched
    whole = score_continuations(lm, extend(lm, [head + t for t in tails]), cands)
    for a, b, c in zip(first, again, whole):
        assert _max_diff(a, b) == 0.0
        assert _max_diff(a, c) < 1e-4


def test_prefix_padding_refused_on_sliding_window(tiny_lm_sliding):
    prefix = extend(tiny_lm_sliding, [tiny_lm_sliding.encode("Valid actions:")])
    with pytest.raises(ValueError, match="equal"):
        extend(tiny_lm_sliding, [[5, 6, 7], [5]], past=prefix)


def test_usage_errors(tiny_lm):
    with pytest.raises(UsageError):
        score_candidates(tiny_lm, ["a", "b"], [CANDS])
    with pytest.raises(UsageError):
        score_candidates(tiny_lm, [""], [CANDS])  # no token to condition on (no <bos>)
    with pytest.raises(UsageError):
        score_candidates(tiny_lm, ["a"], [CANDS], batch_size=0)


def test_candidate_scores_summary():
    scores = CandidateScores.from_logprobs([[-1.0, -2.0], [-0.5], []])
    assert scores.token_counts == [2, 1, 0]
    assert scores.sums == [-3.0, -0.5, 0.0]
    assert scores.best == 2


@pytest.mark.slow
def test_embedded_smollm2_matches_plain_forward(smollm2_cache):
    """Real model: float32 within 1e-4 of the plain computation; bfloat16 within its rounding."""
    from illm_tools.llm.loading import load_model

    contexts = [babyai_context(0), babyai_context(2)]
    lm32 = load_model("smollm2-135m", dtype="float32", cache_dir=smollm2_cache)
    want = [plain_scores(lm32, c, CANDS) for c in contexts]
    for scores, ref in zip(score_candidates(lm32, contexts, [CANDS] * 2, batch_size=2), want):
        assert _max_diff(scores.token_logprobs, ref) < 1e-4
        assert scores.best == max(range(6), key=lambda k: sum(ref[k]))
    lm16 = load_model("smollm2-135m", dtype="bfloat16", cache_dir=smollm2_cache)
    for scores, ref, context in zip(score_candidates(lm16, contexts, [CANDS] * 2, batch_size=2), want, contexts):
        plain16 = plain_scores(lm16, context, CANDS)
        # bfloat16 keeps 8 significant bits: per-token log-probs move by a few hundredths either way;
        # the KV path may not be further from float32 than the plain bf16 forward is, plus that noise
        assert _max_diff(scores.token_logprobs, plain16) < 0.25
        assert _max_diff(scores.token_logprobs, ref) < 2 * _max_diff(plain16, ref) + 0.05
