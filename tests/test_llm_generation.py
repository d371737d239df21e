"""Greedy generation and embeddings on tiny models: batched equals one prompt at a time and
transformers' own greedy `generate`; the summary embedding equals a mean over one forward of
prompt + generated ids; end-of-sequence handling; `embed_texts`."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import babyai_context

from illm_tools.errors import UsageError
from illm_tools.llm.driver import generate
from illm_tools.llm.generation import embed_texts, greedy_from
from illm_tools.llm.scoring import extend

PROMPTS = [babyai_context(i) for i in range(4)] + ["Go", "You see a wall"]


def _last_hidden(lm, ids: list[int]) -> np.ndarray:
    import torch

    with torch.inference_mode():
        out = lm.model(input_ids=torch.tensor([ids]), output_hidden_states=True)
    return out.hidden_states[-1][0].float().numpy()


@pytest.mark.parametrize("fixture", ["tiny_lm", "tiny_lm_sliding"])
def test_batched_equals_one_at_a_time(fixture, request):
    lm = request.getfixturevalue(fixture)
    batched = generate(lm, PROMPTS, max_new_tokens=12, batch_size=4)
    for prompt, got in zip(PROMPTS, batched):
        (alone,) = generate(lm, [prompt], max_new_tokens=12)
        assert got.token_ids == alone.token_ids and got.text == alone.text
        np.testing.assert_allclose(got.embedding, alone.embedding, atol=1e-5)


def test_same_tokens_as_transformers_greedy_generate(tiny_lm_bos):
    import torch
    from transformers import GenerationConfig

    lm = tiny_lm_bos
    config = GenerationConfig(do_sample=False, max_new_tokens=12, eos_token_id=list(lm.eos_ids),
                              pad_token_id=lm.pad_id)
    for prompt, got in zip(PROMPTS[:3], generate(lm, PROMPTS[:3], max_new_tokens=12)):
        ids = torch.tensor([lm.encode(prompt)])
        want = lm.model.generate(ids, attention_mask=torch.ones_like(ids), generation_config=config)
        assert got.token_ids == want[0, ids.shape[1]:].tolist()


def test_embedding_is_mean_over_generated_positions(tiny_lm):
    for prompt, got in zip(PROMPTS[:2], generate(tiny_lm, PROMPTS[:2], max_new_tokens=8)):
        prompt_ids = tiny_lm.encode(prompt)
        hidden = _last_hidden(tiny_lm, prompt_ids + got.token_ids)
        assert got.embedding.dtype == np.float32 and got.embedding.shape == (tiny_lm.hidden_size,)
        np.testing.assert_allclose(got.embedding, hidden[len(prompt_ids):].mean(0), atol=1e-5)
        assert not got.finished and len(got.token_ids) == 8


def test_deterministic(tiny_lm):
    a = generate(tiny_lm, PROMPTS, max_new_tokens=6)
    b = generate(tiny_lm, PROMPTS, max_new_tokens=6)
    for x, y in zip(a, b):
        assert x.token_ids == y.token_ids
        np.testing.assert_array_equal(x.embedding, y.embedding)


def test_stops_at_end_of_sequence_and_excludes_it(tiny_lm):
    (free,) = generate(tiny_lm, [PROMPTS[0]], max_new_tokens=8)
    stop = free.token_ids[2]
    first = free.token_ids.index(stop)  # the token may also occur earlier
    lm = dataclasses.replace(tiny_lm, eos_ids=(stop,))
    (got,) = generate(lm, [PROMPTS[0]], max_new_tokens=8)
    assert got.finished and got.token_ids == free.token_ids[:first]
    assert got.text == tiny_lm.tokenizer.decode(free.token_ids[:first])
    prompt_ids = tiny_lm.encode(PROMPTS[0])
    hidden = _last_hidden(tiny_lm, prompt_ids + free.token_ids[:first + 1])
    if first:
        np.testing.assert_allclose(got.embedding, hidden[len(prompt_ids):-1].mean(0), atol=1e-5)
    else:  # an empty summary is embedded by its end-of-sequence token
        np.testing.assert_allclose(got.embedding, hidden[-1], atol=1e-5)


def test_immediate_end_of_sequence(tiny_lm):
    (free,) = generate(tiny_lm, [PROMPTS[1]], max_new_tokens=2)
    lm = dataclasses.replace(tiny_lm, eos_ids=(free.token_ids[0],))
    (got,) = generate(lm, [PROMPTS[1]], max_new_tokens=4)
    assert got.finished and got.token_ids == [] and got.text == ""
    hidden = _last_hidden(tiny_lm, tiny_lm.encode(PROMPTS[1]) + free.token_ids[:1])
    np.testing.assert_allclose(got.embedding, hidden[-1], atol=1e-5)


def test_rows_ending_at_different_steps_leave_the_batch(tiny_lm):
    """Rows that emit end-of-sequence drop out of the decoding batch (one at once, with an empty
    summary; others later; some never): each row still equals its own run and the free run cut at
    its first end-of-sequence token."""
    free = generate(tiny_lm, PROMPTS, max_new_tokens=8)
    stops = (free[0].token_ids[2], free[1].token_ids[0])
    lm = dataclasses.replace(tiny_lm, eos_ids=stops)
    batched = generate(lm, PROMPTS, max_new_tokens=8, batch_size=len(PROMPTS))
    ends = []
    for prompt, f, got in zip(PROMPTS, free, batched):
        end = next((k for k, t in enumerate(f.token_ids) if t in stops), None)
        ends.append(end)
        assert got.token_ids == f.token_ids[:end] and got.finished == (end is not None)
        (alone,) = generate(lm, [prompt], max_new_tokens=8)
        assert alone.token_ids == got.token_ids
        np.testing.assert_allclose(got.embedding, alone.embedding, atol=1e-5)
    assert ends[1] == 0 and None in ends and len(set(ends)) >= 3  # the case this test is about
    hidden = _last_hidden(tiny_lm, tiny_lm.encode(PROMPTS[1]) + free[1].token_ids[:1])
    np.testing.assert_allclose(batched[1].embedding, hidden[-1], atol=1e-5)


@pytest.mark.parametrize("fixture", ["tiny_lm", "tiny_lm_sliding"])
def test_greedy_from_leaves_its_state_untouched(fixture, request):
    lm = request.getfixturevalue(fixture)
    state = extend(lm, [lm.encode(p) for p in PROMPTS[:3]])
    keys = [layer.keys.clone() for layer in state.cache.layers]
    first = greedy_from(lm, state, 6)
    second = greedy_from(lm, state, 6)
    for (ids_a, fin_a, emb_a), (ids_b, fin_b, emb_b) in zip(first, second):
        assert ids_a == ids_b and fin_a == fin_b
        np.testing.assert_array_equal(emb_a, emb_b)
    assert all(layer.keys.equal(k) for layer, k in zip(state.cache.layers, keys))


@pytest.mark.parametrize("fixture", ["tiny_lm", "tiny_lm_bos"])
def test_embed_texts(fixture, request):
    lm = request.getfixturevalue(fixture)
    texts = ["You see a wall", PROMPTS[0], "Go"]
    got = embed_texts(lm, texts, batch_size=2)
    assert got.shape == (3, lm.hidden_size) and got.dtype == np.float32
    for text, row in zip(texts, got):
        ids = lm.encode(text)
        own = len(ids) - len(lm.bos_ids)
        np.testing.assert_allclose(row, _last_hidden(lm, ids)[-own:].mean(0), atol=1e-5)


def test_usage_errors(tiny_lm):
    with pytest.raises(UsageError):
        generate(tiny_lm, ["Go"], max_new_tokens=0)
    with pytest.raises(UsageError):
        generate(tiny_lm, [""])
    with pytest.raises(UsageError):
        embed_texts(tiny_lm, [""])
