"""The engine's cost by tokens (issue 53): a state's candidates packed behind one copy of its
prompt score as behind a copy each; batches are formed by a token budget and stay under it in
memory; a state longer than the model's context is refused before the engine, in `illm annotate`,
`illm serve` and the live fallback."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest
from conftest import ACTIONS as ACTION_LIST, babyai_context, collect_babyai, plain_scores
from typer.testing import CliRunner

from cli.main import app
from illm_tools.annotate.engine import Annotator
from illm_tools.cache.store import AnnotationCache
from illm_tools.llm.budget import token_batches, token_bytes
from illm_tools.llm.driver import Work, score_candidates, work_tokens
from illm_tools.llm.scoring import plan_state
from illm_tools.tasks.annotation_setup import AnnotationSetup
from illm_tools.tasks.state import StateRecord

pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")
ENV = "BabyAI-GoToLocal-v0"
ACTIONS = tuple(ACTION_LIST)
CANDS = [" " + a for a in ACTIONS]
runner = CliRunner()


def _max_diff(a, b) -> float:
    assert [len(x) for x in a] == [len(y) for y in b]
    return max(abs(x - y) for xs, ys in zip(a, b) for x, y in zip(xs, ys))


def test_token_batches_hold_the_budget_and_the_count():
    costs = [100, 900, 300, 300, 50, 2000, 400]
    batches = token_batches(costs, 3, 1000)
    assert sorted(i for b in batches for i in b) == list(range(len(costs)))
    for b in batches:
        assert len(b) <= 3
        assert len(b) == 1 or len(b) * max(costs[i] for i in b) <= 1000  # a state over the budget alone
    assert [5] in batches  # 2,000 tokens: a batch of its own
    assert token_batches(costs, 3, None) == [[4, 0, 2], [3, 6, 1], [5]]  # no budget: by count, shortest first
    with pytest.raises(Exception, match="batch_size"):
        token_batches(costs, 0, 10)


@pytest.mark.parametrize("fixture", ["tiny_lm", "tiny_lm_bos", "tiny_lm_gpt2"])
def test_packed_candidates_score_as_behind_a_copy_each(fixture, request):
    """Every candidate, every token (those after a boundary the context and candidate share
    included), in a batch of states with different prompt lengths and candidate counts."""
    lm = request.getfixturevalue(fixture)
    repeated = dataclasses.replace(lm, pack_candidates=False)
    contexts = [babyai_context(0), babyai_context(2), "Valid actions: go forward, pick up. Action: "]
    candidates = [CANDS, [" go forward", " drop the red key next to the door", ""], list(ACTIONS)]
    packed = score_candidates(lm, contexts, candidates, batch_size=3)
    copied = score_candidates(repeated, contexts, candidates, batch_size=3)
    for p, c, context, cands in zip(packed, copied, contexts, candidates):
        assert _max_diff(p.token_logprobs, c.token_logprobs) < 1e-5
        assert _max_diff(p.token_logprobs, plain_scores(lm, context, cands)) < 1e-4
        assert p.token_counts == c.token_counts
    plan = plan_state(lm, contexts[0], CANDS)  # what a state holds in the engine, packed and not
    assert work_tokens(lm, Work.scoring(plan)) == len(plan.prefix) + sum(len(c) - 1 for c in plan.continuations)
    assert work_tokens(repeated, Work.scoring(plan)) > len(CANDS) * len(plan.prefix)


@pytest.mark.parametrize("fixture", ["tiny_lm", "tiny_lm_gpt2", "tiny_lm_sliding"])
def test_a_tasks_own_prompt_end_fed_with_its_candidates_scores_as_extended_first(fixture, request):
    """`leads`: the action prompt's tokens after a prefix shared with the summary prompt, packed with
    the candidates (no copy of the prefix for them); a sliding-window model extends first."""
    from illm_tools.llm.scoring import extend, score_continuations

    lm = request.getfixturevalue(fixture)
    tok = lm.tokenizer
    head = lm.encode("You are an expert player playing BabyAI. Valid actions: go forward, drop")
    tails = [tok(t, add_special_tokens=False)["input_ids"] for t in ["\nYou see: a wall.\nAction:", "\nAction:"]]
    if fixture == "tiny_lm_sliding":
        tails[1] = tails[0]  # rows continuing a prefix have one length there
    cands = [[tok(c, add_special_tokens=False)["input_ids"] for c in CANDS], [tok(" go forward")["input_ids"]]]
    prefix = extend(lm, [head, head])
    led = score_continuations(lm, prefix, cands, leads=tails)
    extended = score_continuations(lm, extend(lm, tails, past=prefix), cands)
    for a, b in zip(led, extended):
        assert _max_diff(a, b) < 1e-5


def _long_state(i: int, words: int) -> StateRecord:
    seen = ", ".join(f"a {c} ball {k} steps left" for k, c in zip(range(words), ["red", "green", "blue"] * words))
    return StateRecord("go to the red ball", (), f"You see {seen} ({i})", ACTIONS)


def test_a_state_longer_than_the_context_is_refused_before_the_engine(tiny_lm, tmp_path):
    lm = dataclasses.replace(tiny_lm, context_length=256)
    annotator = Annotator(lm, AnnotationCache(tmp_path / "ann"), model=lm.spec.path, history_len=0)
    short = StateRecord("go to the red ball", (), "You see a red ball 2 steps forward", ACTIONS)
    records = [short, _long_state(1, 60)]
    stats = annotator.annotate_states(records, ENV, "babyai-text@1")
    assert stats.annotated_states == 1 and len(stats.too_long) == 1
    rank, env, tokens = stats.too_long[0]
    assert (rank, env) == (1, ENV) and tokens > 256
    assert annotator.state_too_long(records[1], ENV, "babyai-text@1") == tokens
    assert annotator.state_too_long(short, ENV, "babyai-text@1") is None
    assert len(AnnotationCache(tmp_path / "ann")) == 2  # the short state's two tasks only


def test_the_live_fallback_counts_a_state_too_long_and_trains_on(tiny_lm, tmp_path):
    from illm_tools.rl.live import SyncLive

    lm = dataclasses.replace(tiny_lm, context_length=256)
    annotator = Annotator(lm, AnnotationCache(tmp_path / "ann"), model=lm.spec.path, history_len=0)
    live = SyncLive(annotator, AnnotationSetup(ENV, "babyai-text@1", history_len=0), budget=None)
    short = StateRecord("go to the red ball", (), "You see a red ball 2 steps forward", ACTIONS)
    assert live.submit([_long_state(1, 60), short, _long_state(2, 60)]) == 1
    assert live.too_long == 2 and live.stats()["live_too_long"] == 2.0


def test_the_server_answers_413_for_a_state_longer_than_its_models_context(tiny_lm, tmp_path):
    from fakes import serve_request
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.serve import AnnotationServer, RequestError
    from illm_tools.tasks.prompt_config import PromptConfig

    lm = dataclasses.replace(tiny_lm, context_length=256)
    server = AnnotationServer(lm, AnnotationCache(tmp_path / "ann"), llm=LLMSpec(model=lm.spec.path, dtype="float32"),
                              prompt=PromptConfig(history_len=0))
    short = StateRecord("go to the red ball", (), "You see a red ball 2 steps forward", ACTIONS)
    body = json.loads(json.dumps(serve_request([(short, 1), (_long_state(1, 60), 1)],
                                               model_fingerprint=server.fingerprint)))
    with pytest.raises(RequestError, match=r"needs \d+ tokens, more than the context of the server's model \(256\)") as e:
        server.submit(body)
    assert e.value.status == 413 and server.queue_size() == 0  # nothing of the request queued
    assert server.submit(json.loads(json.dumps(serve_request([(short, 1)], model_fingerprint=server.fingerprint))))[
        "queued"] == 1


def test_annotate_names_and_skips_the_states_longer_than_the_context(tiny_lm, tmp_path_factory, tmp_path):
    folder = tmp_path / "short-context"
    shutil.copytree(tiny_lm.spec.path, folder)
    config = json.loads((folder / "config.json").read_text())
    config["max_position_embeddings"] = 96  # BabyAI's history-3 prompts are longer
    (folder / "config.json").write_text(json.dumps(config))
    traj = collect_babyai(tmp_path_factory, steps=24, seed=3, action_space="augmented")
    out = runner.invoke(app, ["annotate", str(traj), "--cache", str(tmp_path / "ann"), "--model", str(folder),
                              "--dtype", "float32", "--history", "3", "--tasks", "action", "--limit", "4"])
    assert out.exit_code == 0, out.output
    assert "skipped 4 states longer than the model's context (most visited first): #1 of BabyAI-GoToLocal-v0 (" in \
        out.output and "a shorter --history" in out.output
    assert not (tmp_path / "ann").exists() or len(AnnotationCache(tmp_path / "ann")) == 0


def _crafter_like(i: int) -> StateRecord:
    """A long prompt (about 600 tokens) with 17 candidates, as Crafter's at history 3."""
    seen = "; ".join(f"{m} {k} steps {d}" for k, (m, d) in enumerate(
        zip(["tree", "stone", "water", "grass", "sand", "coal", "iron", "table"] * 12, ["north", "south", "east", "west"] * 24)))
    actions = ("noop", "move left", "move right", "move up", "move down", "do", "sleep", "place stone", "place table",
               "place furnace", "place plant", "make wood pickaxe", "make stone pickaxe", "make iron pickaxe",
               "make wood sword", "make stone sword", "make iron sword")
    return StateRecord("survive and unlock achievements", (), f"You see {seen} ({i}).", actions)


@pytest.mark.slow  # 30 s: SmolLM2, a batch of long prompts through both paths
def test_a_batch_of_long_prompts_stays_under_its_token_budget_in_memory(smollm2_cache):
    """Peak resident memory (VmHWM, reset before each pass) above the start: the packed batch
    under what the budget allows it, the copied one (17 prompt copies a state) far over it."""
    from illm_tools.llm.loading import load_model

    def peak_growth(model, contexts, candidates) -> float:
        with open("/proc/self/status") as f:
            base = next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        score_candidates(model, contexts, candidates, batch_size=16)
        with open("/proc/self/status") as f:
            return (next(int(line.split()[1]) for line in f if line.startswith("VmHWM")) - base) * 1024

    lm = load_model("smollm2-135m", dtype="float32", cache_dir=smollm2_cache)
    states = [_crafter_like(i) for i in range(4)]
    contexts = [f"{s.mission}. {s.observation} Valid actions: {', '.join(s.valid_actions)}. Action:" for s in states]
    candidates = [[" " + a for a in s.valid_actions] for s in states]
    widest = max(work_tokens(lm, Work.scoring(plan_state(lm, c, k))) for c, k in zip(contexts, candidates))
    assert widest > 500
    lm = dataclasses.replace(lm, batch_tokens=4 * widest)  # all four in one batch
    allowed = lm.batch_tokens * token_bytes(lm.model)
    score_candidates(lm, contexts[:1], candidates[:1])  # warm the allocator and the kernels
    packed = peak_growth(lm, contexts, candidates)
    copied = peak_growth(dataclasses.replace(lm, pack_candidates=False, batch_tokens=None), contexts, candidates)
    assert packed < allowed < copied, (packed / 2**20, allowed / 2**20, copied / 2**20)


def _at_every_limit(limits) -> StateRecord:
    """A state at each per-field limit of `illm serve` (history 0): mission and observation of
    `max_text_chars`, `max_actions` distinct actions of `max_action_chars`."""
    import random

    rng = random.Random(0)
    words = "red green blue grey purple yellow ball key box door wall steps left right forward you see a".split()

    def text(n: int) -> str:
        out = ""
        while len(out) < n:
            out += rng.choice(words) + " "
        return out[:n]

    actions = tuple(f"{i:02d} {text(limits.max_action_chars)}"[: limits.max_action_chars] for i in range(limits.max_actions))
    return StateRecord(text(limits.max_text_chars), (), text(limits.max_text_chars), actions)


@pytest.mark.slow  # 30-140 s: SmolLM2 served (in the dtype --dtype auto picks), one state at every limit annotated
def test_a_state_at_every_serve_limit_grows_the_server_within_its_stated_bound(smollm2_cache, tmp_path):
    """The server's peak resident memory (its VmHWM, reset after a warm-up batch) grows by less than
    docs/commands/serve.md states for one state at every limit, while another trainer's states land."""
    import os
    import re
    import subprocess
    import sys
    from fakes import call, serve_request, wait_for
    from illm_tools.serve import ServeLimits

    env = {**os.environ, "HF_HUB_OFFLINE": "1", "ILLM_CACHE_DIR": str(smollm2_cache)}
    env.pop("ILLM_SERVE_TOKEN", None)
    proc = subprocess.Popen([sys.executable, "-m", "cli.main", "serve", "--cache", str(tmp_path / "ann"), "--model",
                             "smollm2-135m", "--history", "0", "--port", "0"],
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        found = re.search(r"http://127\.0\.0\.1:(\d+)", proc.stderr.readline())
        assert found, proc.stderr.read()
        url = f"http://127.0.0.1:{found.group(1)}"
        fingerprint = call(url + "/stats")[1]["model_fingerprint"]

        def post(states, client: str) -> tuple[int, dict]:
            body = serve_request([(s, 1) for s in states], client=client, model_fingerprint=fingerprint)
            return call(url + "/annotate", json.loads(json.dumps(body)))

        def annotated(n: int) -> bool:  # what the server reports, however long the machine takes
            stats = call(url + "/stats")[1]
            return stats["annotated_states"] >= n and not stats["queue"] and not stats["annotating"]

        small = [StateRecord("go to the red ball", (), f"You see a red ball {k} steps forward", ACTIONS) for k in range(4)]
        assert post(small[:2], "warm-up")[0] == 202
        wait_for(lambda: annotated(2), 1200, "the warm-up batch")  # the model's first batch: kernels, allocator
        status_file = f"/proc/{proc.pid}/status"
        with open(status_file) as f:
            before = next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024
        with open(f"/proc/{proc.pid}/clear_refs", "w") as f:
            f.write("5")
        assert post([_at_every_limit(ServeLimits())], "at-the-limits")[1]["queued"] == 1
        assert post(small[2:], "another-trainer")[1]["queued"] == 2
        wait_for(lambda: annotated(5), 1200, "the state at every limit and the other trainer's two")
        with open(status_file) as f:
            peak = next(int(line.split()[1]) for line in f if line.startswith("VmHWM")) / 1024
        stats = call(url + "/stats")[1]
        assert stats["annotated_states"] == 5 and stats["errors"] == 0 and stats["failed_states"] == 0, stats
        assert peak - before < stated_bound_mb(), (before, peak)
    finally:
        proc.send_signal(2)
        proc.communicate(timeout=60)


def stated_bound_mb() -> float:
    """docs/commands/serve.md's bound on the growth of a server's resident memory by one state at
    every limit ("grows the server's resident memory by **at most N GiB**"), in MB."""
    import re
    from pathlib import Path

    page = (Path(__file__).parents[1] / "docs" / "commands" / "serve.md").read_text()
    found = re.search(r"resident memory by \*\*at most ([\d.]+) GiB\*\*", page)
    assert found, "docs/commands/serve.md states no bound for one state at every limit"
    return float(found.group(1)) * 1024
