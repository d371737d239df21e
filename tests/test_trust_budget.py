"""Every engine-bound state measured in tokens (issue 69, findings 3 and 9): a hop state's head,
window of translated steps, tail and candidates against the model's context, refused at arrival as
a text state is; the packed candidates' mask, which grows with the square of a state's candidate
tokens, counted in a batch's token budget, and a state whose mask alone is over the budget scored
in groups of candidates whose masks fit."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import plain_scores

from illm_tools.annotate.engine import HOP_MARK, Annotator
from illm_tools.cache.store import AnnotationCache
from illm_tools.llm.budget import mask_bytes, mask_tokens, token_batches, token_bytes
from illm_tools.llm.packed import mask_groups, packed_mask
from illm_tools.llm.driver import Work, batches, score_candidates, work_shape, work_tokens
from illm_tools.llm.scoring import plan_state
from illm_tools.tasks.registry import get_task

pytestmark = pytest.mark.usefixtures("model_cache_in_tmp", "one_torch_thread")
HOP = {"renderer": "hop@2:seed=0:beta=100.0:window=2", "history_len": 1, "env_id": "MiniGrid-MultiRoom-N6-v0"}
ACTIONS = ("left", "right", "forward")
CONTEXT = "You are an expert player playing BabyAI. Valid actions: go forward, drop. Action:"


def _hop_records(mission: str, n: int = 2):
    """Hop records of one episode's first `n` steps (window 2) under `mission`."""
    from illm_tools.hop.context import HopTracker

    tracker, rng, out = HopTracker(1, 1, ACTIONS), np.random.default_rng(0), []
    for _ in range(n):
        (record,) = tracker.records([mission], [rng.integers(0, 9, (7, 7, 3), dtype=np.uint8)])
        out.append(record)
        tracker.push([2], [False])
    return out


def _hop_server(lm, tmp_path):
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.serve import AnnotationServer
    from illm_tools.tasks.prompt_config import PromptConfig

    return AnnotationServer(lm, AnnotationCache(tmp_path / "ann"), llm=LLMSpec(model=lm.spec.path, dtype="float32"),
                            prompt=PromptConfig(history_len=1))


def _expected_hop_tokens(lm, annotator, record) -> int:
    """What a hop state takes in the spliced engine, counted here from its parts: per task, the head's
    tokens, one position per translated step, the tail's tokens, then its longest candidate or the
    tokens it generates; the most of its tasks."""
    builder = annotator.builder(HOP["env_id"], HOP["renderer"])
    tokens = lambda text: len(lm.tokenizer(text, add_special_tokens=False)["input_ids"])  # noqa: E731
    most = 0
    for task in annotator.tasks:
        head, tail = builder.render(task, record, HOP_MARK).text.split(HOP_MARK)
        prompt = builder.render(task, record, "")
        after = max((tokens(c) for c in prompt.candidates or ()), default=0) + get_task(task).max_new_tokens
        most = max(most, len(lm.encode(head)) + len(record.frames) + tokens(tail) + after)
    return most


def test_a_hop_state_longer_than_the_context_is_refused_at_arrival(tiny_lm, tmp_path):
    """The finding's request: a hop state whose prompt head alone is over the model's context was
    queued; now it is answered 413 as a text state is, naming the tokens it needs, nothing queued."""
    from fakes import serve_request
    from illm_tools.serve import RequestError

    lm = dataclasses.replace(tiny_lm, context_length=256)
    server = _hop_server(lm, tmp_path)
    (_, long_state) = _hop_records("get to the green goal square behind the purple door " * 12)
    head_tokens = len(lm.encode("get to the green goal square behind the purple door " * 12))
    assert head_tokens > 256  # the mission alone is over the context
    needed = _expected_hop_tokens(lm, server.annotator, long_state)
    body = json.loads(json.dumps(serve_request([(long_state, 1)], model_fingerprint=server.fingerprint, **HOP)))
    with pytest.raises(RequestError, match=rf"a state needs {needed:,} tokens, more than the context of the "
                                           r"server's model \(256\)") as e:
        server.submit(body)
    assert e.value.status == 413 and server.queue_size() == 0
    assert len(str(e.value).splitlines()) == 1
    (_, short) = _hop_records("get to the green goal square")
    assert server.annotator.state_too_long(short, HOP["env_id"], HOP["renderer"]) is None
    body = json.loads(json.dumps(serve_request([(short, 1)], model_fingerprint=server.fingerprint, **HOP)))
    assert server.submit(body)["queued"] == 1


def test_annotate_counts_a_hop_state_too_long_and_annotates_the_rest(tiny_lm, tmp_path):
    """`illm annotate` and the live fallback (the annotator's plan): the long hop state is counted in
    `too_long` with the tokens it needs and never reaches the spliced engine; the short one does,
    in batches within a small token budget."""
    lm = dataclasses.replace(tiny_lm, context_length=256, batch_tokens=64)
    annotator = Annotator(lm, AnnotationCache(tmp_path / "ann"), model=lm.spec.path, history_len=1)
    short = _hop_records("get to the green goal square")
    long_state = _hop_records("get to the green goal square behind the purple door " * 12)[1]
    stats = annotator.annotate_states([*short, long_state], HOP["env_id"], HOP["renderer"])
    assert [(env, tokens) for _rank, env, tokens in stats.too_long] == [
        (HOP["env_id"], _expected_hop_tokens(lm, annotator, long_state))]
    assert stats.annotated_states == 2 and stats.rows == 2 * len(annotator.tasks)


def test_the_mask_s_bytes_are_what_packed_mask_holds(tiny_lm):
    """The budget's arithmetic: entries x (the compute dtype's bytes + the bool it is built from);
    in tokens, rounded up; and `packed_mask` at its peak holds no more (VmHWM, reset before)."""
    import torch

    model = tiny_lm.model
    assert mask_bytes(model, 2, 300, 50) == 2 * 300 * 350 * (4 + 1)
    assert mask_tokens(model, 2, 300, 50) == -(-2 * 300 * 350 * 5 // token_bytes(model))
    assert mask_tokens(model, 2, 0, 50) == 0

    def status(key: str) -> int:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(key)) * 1024

    fed, prefix = 6000, 40
    owner = (torch.arange(fed) // 150)[None]
    packed_mask(torch.ones(1, prefix, dtype=torch.long), owner[:, :10], torch.float32)  # warm
    before = status("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    mask = packed_mask(torch.ones(1, prefix, dtype=torch.long), owner, torch.float32)
    peak = status("VmHWM") - before
    assert mask.shape == (1, 1, fed, prefix + fed)
    # at least the mask itself (within 1%: a worker's resident pages freed while it is built count against it;
    # 2.5 kB short of the mask's 145 MB was seen in a full `make test`), at most the budget's arithmetic
    assert mask.numel() * 4 * 0.99 < peak <= mask_bytes(model, 1, fed, prefix) * 1.02, (peak, mask_bytes(model, 1, fed, prefix))


def _many_long_candidates(lm, k: int = 12, words: int = 40) -> list[str]:
    return [" " + " ".join(f"pick up the {c} key {i}" for c in ("red", "blue", "grey", "green")[: 1 + i % 4]) * (words // 4)
            for i in range(k)]


def test_a_batch_s_budget_counts_its_mask(tiny_lm):
    """Two states of many long candidates fit a budget by their tokens alone (2 x the widest), not
    with their masks: they go in batches of their own; without packing (no mask) they share one."""
    cands = _many_long_candidates(tiny_lm)
    plans = [plan_state(tiny_lm, CONTEXT, cands), plan_state(tiny_lm, CONTEXT + " Now:", cands)]
    works = [Work.scoring(p) for p in plans]
    costs, shapes = [work_tokens(tiny_lm, w) for w in works], [work_shape(w) for w in works]
    prefix, fed = max(s[0] for s in shapes), max(s[1] for s in shapes)
    assert fed > 1000 and shapes[0][0] + shapes[0][1] == costs[0]
    padded = 2 * max(costs) + mask_tokens(tiny_lm.model, 2, fed, prefix)
    lm = dataclasses.replace(tiny_lm, batch_tokens=padded - 1)
    assert 2 * max(costs) <= lm.batch_tokens  # the tokens alone fit
    assert token_batches(costs, 8, lm.batch_tokens) == [[0, 1]]
    assert batches(lm, costs, shapes, 8) == [[0], [1]]
    assert batches(dataclasses.replace(lm, batch_tokens=padded), costs, shapes, 8) == [[0, 1]]
    assert token_batches(costs, 8, padded - 1, shapes, lambda rows, f, p: mask_tokens(tiny_lm.model, rows, f, p)) \
        == [[0], [1]]


def test_a_state_whose_mask_alone_is_over_the_budget_is_scored_in_groups(tiny_lm):
    """Its candidates are scored in groups behind the one cached prefix, each group's mask within the
    budget; the scores are those of one packed forward and of a forward per candidate; the peak
    memory is a group's, not the whole mask's."""
    cands = _many_long_candidates(tiny_lm, k=24, words=80)
    plan = plan_state(tiny_lm, CONTEXT, cands)
    prefix, fed = work_shape(Work.scoring(plan))
    whole = mask_tokens(tiny_lm.model, 1, fed, prefix)
    lm = dataclasses.replace(tiny_lm, batch_tokens=whole // 8)
    groups = mask_groups(lm, prefix, [plan.continuations])
    assert len(groups) > 2 and groups[0][0] == 0 and groups[-1][1] == len(cands)
    assert all(a[1] == b[0] for a, b in zip(groups, groups[1:]))
    for start, end in groups:
        group_fed = sum(len(c) - 1 for c in plan.continuations[start:end])
        assert end - start == 1 or mask_tokens(lm.model, 1, group_fed, prefix) <= lm.batch_tokens
    assert mask_groups(dataclasses.replace(lm, batch_tokens=whole), prefix, [plan.continuations]) == [(0, len(cands))]

    grouped = score_candidates(lm, [CONTEXT], [cands])[0]
    whole_forward = score_candidates(dataclasses.replace(lm, batch_tokens=None), [CONTEXT], [cands])[0]
    assert grouped.token_counts == whole_forward.token_counts
    assert max(abs(a - b) for x, y in zip(grouped.token_logprobs, whole_forward.token_logprobs)
               for a, b in zip(x, y)) < 1e-5
    reference = plain_scores(tiny_lm, CONTEXT, cands[:3])
    assert max(abs(a - b) for x, y in zip(grouped.token_logprobs[:3], reference) for a, b in zip(x, y)) < 1e-4


def test_the_shared_prefix_path_groups_a_states_candidates_with_its_lead(tiny_lm):
    """`score_and_generate` (the action prompt's own end fed with its candidates): with the budget
    under the state's mask, the same scores and the same summary as with room for the whole mask."""
    from illm_tools.llm.driver import score_and_generate

    cands = _many_long_candidates(tiny_lm, k=16, words=40)
    contexts, prompts = [CONTEXT + " What do you do?\nAction:"], [CONTEXT + " Summarize the main points:"]
    roomy = dataclasses.replace(tiny_lm, batch_tokens=10**7)
    tight = dataclasses.replace(tiny_lm, batch_tokens=2000)
    (wide,), (wide_gen,) = score_and_generate(roomy, contexts, [cands], prompts, max_new_tokens=8)
    (grouped,), (grouped_gen,) = score_and_generate(tight, contexts, [cands], prompts, max_new_tokens=8)
    plan = plan_state(tight, contexts[0], cands)
    prefix, fed = work_shape(Work.scoring(plan))
    assert mask_tokens(tight.model, 1, fed, prefix) > tight.batch_tokens  # its mask alone: grouped
    assert grouped.token_counts == wide.token_counts and grouped_gen.token_ids == wide_gen.token_ids
    assert max(abs(a - b) for x, y in zip(grouped.token_logprobs, wide.token_logprobs) for a, b in zip(x, y)) < 1e-5


def test_grouping_bounds_the_peak_memory_of_a_state_of_many_long_candidates(tiny_lm):
    """VmHWM (reset before) while scoring one state whose whole mask is ~200 MB with a budget of an
    eighth of it: the growth stays under a quarter of the whole mask."""
    cands = [" " + "é" * 200 + str(i) for i in range(16)]  # a byte a token: 16 x ~400 tokens
    plan = plan_state(tiny_lm, CONTEXT, cands)
    prefix, fed = work_shape(Work.scoring(plan))
    whole = mask_bytes(tiny_lm.model, 1, fed, prefix)
    assert whole > 100 * 2**20
    lm = dataclasses.replace(tiny_lm, batch_tokens=mask_tokens(tiny_lm.model, 1, fed, prefix) // 8)
    score_candidates(lm, [CONTEXT], [cands[:2]])  # warm the allocator and kernels

    def status(key: str) -> int:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(key)) * 1024

    before = status("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    score_candidates(lm, [CONTEXT], [cands])
    growth = status("VmHWM") - before
    assert growth < whole / 4, (growth / 2**20, whole / 2**20)
