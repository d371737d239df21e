"""Language tasks: template versions are pinned, history follows paper B.1, keys are stable and
sensitive, records from a table equal records from live tracking, calibrations behave; the setup
module makes the writer's and the reader's keys alike and reads, adopts and checks a cache's setups."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from illm_tools.errors import UsageError
from illm_tools.tasks.calibration import action_distribution
from illm_tools.tasks.prompts import format_history, template_sha
from illm_tools.tasks.registry import LANGUAGE_TASKS
from illm_tools.tasks.state import HistoryTracker, StateRecord, records_from_table
from fakes import ACTIONS, prompt_builder as builder, state_record as record

# Changing a template's text must bump its version in VERSIONS and the hash here.
PINNED = {
    ("action.paper", 2): "8797f2a94cc4ff38",  # 2: as printed (B.2), without the "Answer:" cue of version 1
    ("action.shared", 1): "e26ba63753ebba15",
    ("summary", 1): "176b9227a05ae00e",
    ("goal", 1): "237d50b4c0e62685",
    ("plan", 1): "4395f3ba8de9e629",
}



@pytest.mark.parametrize("name,version", sorted({tv for t in LANGUAGE_TASKS.values() for tv in t.templates.values()}))
def test_template_text_is_pinned_to_its_version(name, version):
    assert template_sha(name) == PINNED[(name, version)]


def test_history_follows_paper_b1():
    rec = record(history=[("You see a wall 2 steps forward", "turn left"), ("You see nothing", "go forward")])
    assert format_history(rec) == (
        "\nObservation 0: You see a wall 2 steps forward\nAction 0: turn left\n"
        "Observation 1: You see nothing\nAction 1: go forward\n"
        "Observation 2: You see a red ball 1 step forward"
    )


def test_prompts_carry_the_paper_text_and_candidates():
    b = builder(layout="paper")
    p = b.render("action", record())
    assert p.text.startswith("You are an expert player playing BabyAI. The goal is: go to the red ball.\n")
    assert "Valid actions: turn left, turn right, go forward, pick up, drop, toggle\nYou see: \n" in p.text
    assert p.candidates == tuple(" " + a for a in ACTIONS)
    s = b.render("summary", record())
    assert "Summarize the main points of the player's history into a short text:" in s.text
    assert s.candidates is None


def test_the_paper_layout_is_the_printed_prompt():
    """Paper B.2's action and summary prompts as printed, {task}, {possible actions ...} and {agent
    history} filled in; what differs is in the README ("Prompts"): the printed ''Eat door'' (LaTeX
    quotes) is written "Eat door", the summary prompt's "history::" has one colon, and the printed
    line breaks inside the instruction are the typesetting's."""
    rec = record(history=[("You see a wall 2 steps forward", "turn left")])
    b = builder(layout="paper", history_len=1)
    assert b.render("action", rec).text == (
        "You are an expert player playing BabyAI. The goal is: go to the red ball.\n"
        "Valid actions: turn left, turn right, go forward, pick up, drop, toggle\n"
        "You see: \nObservation 0: You see a wall 2 steps forward\nAction 0: turn left\n"
        "Observation 1: You see a red ball 1 step forward\n"
        "Suggest the best action the player can take. Do not recommend actions that are not possible or not "
        "desirable, such as \"Eat door\". Prioritize actions which involve the object you are facing or which the "
        "agent has not achieved before. What do you do?")
    assert b.render("summary", rec).text == (
        "You are an expert player playing BabyAI. The goal is: go to the red ball.\n"
        "Recent player's history: \nObservation 0: You see a wall 2 steps forward\nAction 0: turn left\n"
        "Observation 1: You see a red ball 1 step forward\n"
        "Summarize the main points of the player's history into a short text:")


def test_shared_layout_puts_the_history_in_a_common_prefix():
    b = builder(layout="shared")
    a, s = b.render("action", record()), b.render("summary", record())
    head = "Recent player's history: " + a.history + "\n"
    assert head in a.text and head in s.text
    assert a.text.index(head) == s.text.index(head)


def test_keys_are_stable_and_sensitive():
    b = builder()
    p = b.render("action", record())
    assert b.key(p) == builder().key(builder().render("action", record()))
    changed = [
        builder(model_fingerprint="e" * 16).key(p),
        builder(renderer="babyai-text@2").key(p),
        builder(layout="paper").key(builder(layout="paper").render("action", record())),
        b.key(b.render("action", record(obs="You see a wall 1 step forward"))),
        b.key(b.render("summary", record())),
        builder(history_len=2).key(builder(history_len=2).render("action", record(history=[("a", "drop")]))),
    ]
    assert len({b.key(p), *changed}) == len(changed) + 1


AWKWARD = ["", "  ", "plain", 'a "quoted" word', "back\\slash", "tab\there", "two\nlines\r\nthree", "é ü 中文 🙂",
           "\x00\x01\x1f ctl", "\u2028 sep", "{history} {task}", "\x00illm-history\x00"]


@pytest.mark.parametrize("layout", ["shared", "paper"])
def test_state_keys_are_the_rendered_prompts_keys_on_awkward_texts(layout):
    """`state_keys` (computed without rendering, `illm_tools.tasks.state_keys`) equals the key of
    each task's rendered prompt: every layout and task, histories of every length, texts with
    quotes, escapes, control characters, newlines, unicode and the template's own field names."""
    import itertools

    tasks = ("action", "summary", "goal", "plan")
    for k, (mission, obs, act) in enumerate(itertools.product(AWKWARD[::3] + ["go to the red ball"], AWKWARD, ACTIONS[:2])):
        b = builder(layout=layout, history_len=k % 4)
        history = [(AWKWARD[(k + i) % len(AWKWARD)], act) for i in range(k % 4)]
        rec = StateRecord(mission, tuple(history), obs, ACTIONS if k % 2 else (act, 'say "hi"'))
        for _ in range(2):  # the second time from its memos
            assert b.state_keys(rec, tasks) == tuple(b.key(b.render(t, rec)) for t in tasks), (mission, obs, history)
        assert all(frame is not None for frame in b._state_keys._frames.values()) or "\x00" in mission  # the fast path ran


def test_state_keys_memos_keep_observations_actions_and_places_apart():
    """One builder keys states whose texts recur as observations (written on one line) and as
    actions (verbatim), at every place of the history: each key is still its rendered prompt's."""
    b = builder(history_len=3)
    texts = ["two\nlines", "  padded  ", "", "turn left", 'say "hi"']
    records = [StateRecord("go to the red ball", tuple((texts[(i + j) % 5], texts[(i + 2 * j) % 5]) for j in range(n)),
                           texts[i], ACTIONS) for i in range(5) for n in range(4)]
    for rec in records + records[::-1]:
        assert b.state_keys(rec) == tuple(b.key(b.render(t, rec)) for t in ("action", "summary")), rec


def test_bad_layout_is_refused():
    with pytest.raises(UsageError, match="layout"):
        builder(layout="fancy")


def test_records_from_a_table_equal_live_tracking():
    # Two envs, interleaved rows, episode boundary in env 0 after step 2.
    steps = [  # (episode, step, text, action index, done)
        (0, 0, "a0", 0, False), (1, 0, "b0", 1, False), (0, 1, "a1", 2, False), (1, 1, "b1", 3, False),
        (0, 2, "a2", 4, True), (1, 2, "b2", 5, False), (2, 0, "c0", 0, False), (1, 3, "b3", 1, False),
    ]
    table = pa.table({
        "episode_id": [s[0] for s in steps], "step": [s[1] for s in steps],
        "env_id": ["BabyAI-GoToLocal-v0"] * len(steps), "mission": ["go"] * len(steps),
        "obs_text": [s[2] for s in steps], "action_text": [ACTIONS[s[3]] for s in steps],
        "valid_actions": [list(ACTIONS)] * len(steps),
    })
    from_table, _ = records_from_table(table, history_len=2)
    tracker = HistoryTracker(2, 2, ACTIONS)
    live = []
    for t in range(0, len(steps), 2):
        pair = steps[t:t + 2]
        live += tracker.records(["go", "go"], [s[2] for s in pair])
        tracker.push([s[2] for s in pair], [s[3] for s in pair], [s[4] for s in pair])
    assert from_table == live
    assert from_table[5].history == (("b0", "turn right"), ("b1", "pick up"))
    assert from_table[6].history == ()


def test_calibrations():
    sums = np.array([[-2.0, -4.0, -9.0]])
    counts = np.array([[1, 2, 3]])
    neutral = np.array([[-1.0, -5.0, -9.5]])
    assert action_distribution(sums, counts, neutral, "sum").argmax() == 0
    assert np.allclose(action_distribution(sums, counts, neutral, "mean"),
                       np.exp([-2, -2, -3]) / np.exp([-2, -2, -3]).sum())
    assert action_distribution(sums, counts, neutral, "pmi").argmax() == 1
    assert np.allclose(action_distribution(sums, counts, neutral, "sum").sum(), 1.0)


def test_one_setup_module_makes_the_keys_reads_a_caches_setups_adopts_and_checks(tmp_path):
    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.errors import CacheError
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.tasks.annotation_setup import AnnotationSetup, SetupOptions, adopt, cache_setups, check_setup

    llm = LLMSpec(backend="stub", dtype="float32", quant="none", device="cpu")
    setup = AnnotationSetup("BabyAI-GoToLocal-v0", "babyai-text@1", ("action", "summary"), history_len=1)
    cache = AnnotationCache(tmp_path / "ann")
    annotator = Annotator.of_setup(llm.load(), cache, llm, setup)
    assert annotator.builder(setup.env_id, setup.renderer) == setup.builder_of(llm)  # the writer's keys: the reader's
    assert adopt(tmp_path / "ann", setup.tasks, setup.renderer) is None  # no cache in the folder yet
    annotator.annotate_states([record(), record("You see a wall 1 step forward")], setup.env_id, setup.renderer)
    held = cache_setups(tmp_path / "ann", setup.tasks, setup.renderer)  # a cache's folder, or the cache
    assert held == [SetupOptions("stub", llm.model, "float32", "none", 1, "shared", "babyai-text@1", entries=2,
                              model_fingerprint=llm.fingerprint(), served_at=(llm.model,))]
    assert held[0].options().endswith("--history 1 --layout shared") and held[0].fields()["model_dtype"] == "float32"
    assert adopt(cache, setup.tasks, setup.renderer) == held[0] and cache_setups(cache, setup.tasks, "other@1") == []
    check_setup(cache, setup.builder_of(llm), llm=llm, tasks=setup.tasks)  # its own setup: nothing refused
    other = AnnotationSetup(setup.env_id, setup.renderer, setup.tasks, history_len=0)
    with pytest.raises(CacheError, match="holds --history 1 annotations .*this run asks for --history 0"):
        check_setup(cache, other.builder_of(llm), llm=llm, tasks=setup.tasks)
