"""`illm probe`: the metrics on hand-made rankings with known answers, the bot's states, the
command on the stub backend, and a level without an expert refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.probe import (agreement, agreement_per_action, expert_states, log_loss, mutual_information_bits,
                              pairwise_auroc, top_choice_entropy_bits)

runner = CliRunner()


def test_metrics_have_their_known_values():
    expert = np.array([0, 1, 2, 1])
    perfect = np.eye(3)[expert] * 5.0
    assert agreement(perfect, expert) == 1.0 and pairwise_auroc(perfect, expert) == 1.0
    assert agreement(-perfect, expert) == 0.0 and pairwise_auroc(-perfect, expert) == 0.0
    flat = np.zeros((4, 3))
    assert pairwise_auroc(flat, expert) == 0.5  # ties count one half
    assert agreement(flat, expert) == 0.25  # ties go to the first action: right in state 0 only
    same = np.tile([0.7, 0.2, 0.1], (4, 1))  # a ranking that ignores the state
    assert mutual_information_bits(same) == pytest.approx(0.0, abs=1e-12)
    assert top_choice_entropy_bits(same) == 0.0
    onehot = np.eye(3)[[0, 1, 2, 0]]
    assert mutual_information_bits(onehot) == pytest.approx(1.5)  # H(.5,.25,.25) - 0
    assert top_choice_entropy_bits(onehot) == pytest.approx(1.5)
    assert log_loss(np.full((4, 3), 1 / 3), expert) == pytest.approx(np.log(3))
    half = np.eye(3)[[0, 1, 0, 0]]  # right in states 0 and 1; wrong in state 2 (action 2) and 3 (the second 1)
    assert agreement_per_action(half, expert, ("a", "b", "c", "d")) == {"a": 1.0, "b": 0.5, "c": 0.0}  # d: never taken


def test_the_bots_states_are_seeded_and_labelled_with_valid_actions():
    a = expert_states("BabyAI-GoToLocal-v0", 40, history=1, seed=3)
    b = expert_states("BabyAI-GoToLocal-v0", 40, history=1, seed=3)
    assert a.records == b.records and a.expert.tolist() == b.expert.tolist() and len(a.records) == 40
    assert a.actions == ("turn left", "turn right", "go forward")  # GoTo levels: the original 3 actions
    assert set(a.expert.tolist()) <= {0, 1, 2} and all(len(r.history) <= 1 for r in a.records)
    assert a.records != expert_states("BabyAI-GoToLocal-v0", 40, history=1, seed=4).records
    greedy = expert_states("BabyAI-GoToLocal-v0", 200, seed=0, epsilon=0.0)
    assert greedy.episodes > 1  # with no random actions the bot finishes its episodes
    irrelevant = expert_states("BabyAI-GoToLocal-v0", 60, seed=0, action_space="irrelevant")
    assert len(irrelevant.actions) == 9 and irrelevant.expert.max() < 6  # never sleep/do nothing/think (MiniGrid's done)


def test_probe_prints_its_table_and_json(tmp_path):
    args = ["probe", "--backend", "stub", "--model", "stub:16", "--states", "30", "--out", str(tmp_path / "p.json")]
    out = runner.invoke(app, args)
    assert out.exit_code == 0, out.output
    assert "LLM, pmi" in out.output and "always go forward" in out.output and "reading:" in out.output
    assert "agreement per expert action" in out.output
    figures = json.loads((tmp_path / "p.json").read_text())
    assert figures["states"] == 30 and set(figures["calibrations"]) == {"sum", "mean", "pmi"}
    assert 0.0 <= figures["calibrations"]["sum"]["auroc"] <= 1.0
    as_json = runner.invoke(app, [*args[:-2], "--json"])
    assert json.loads(as_json.output)["baselines"] == figures["baselines"]


def test_a_level_without_an_expert_is_refused_in_one_line():
    out = runner.invoke(app, ["probe", "--env", "MiniGrid-MultiRoom-N6-v0", "--backend", "stub", "--states", "5"])
    assert out.exit_code == 1 and "has no expert to compare with" in out.output
    assert len(out.output.strip().splitlines()) == 1


def test_unknown_env_is_refused_in_one_line():
    out = runner.invoke(app, ["probe", "--env", "BabyAI-NoSuchLevel-v0", "--backend", "stub", "--states", "5"])
    assert out.exit_code == 1 and "unknown environment id" in out.output
    assert len(out.output.strip().splitlines()) == 1


def test_auroc_counts_ties_as_half_per_state():
    scores = np.array([[1.0, 1.0, 0.0], [3.0, 2.0, 2.0]])  # the expert ties one rival, beats / loses to the other
    assert pairwise_auroc(scores, np.array([0, 1])) == pytest.approx(np.mean([0.75, 0.25]))
    assert agreement(scores, np.array([0, 1])) == 0.5
    assert agreement(scores[:1], np.array([0])) == 1.0 and agreement(scores[:1], np.array([1])) == 0.0  # ties: first


def test_the_probes_scores_are_the_annotators(tiny_lm):
    """The probe renders and scores each state exactly as `illm annotate --tasks action` would."""
    from illm_tools.annotate.engine import Annotator, Job
    from illm_tools.keys import fingerprint_hash
    from illm_tools.llm.backend import as_backend
    from illm_tools.probe import score_records
    from illm_tools.tasks.prompts import PromptBuilder

    lm = as_backend(tiny_lm)
    states = expert_states("BabyAI-GoToLocal-v0", 12, history=2, seed=1)
    builder = PromptBuilder(env_id="BabyAI-GoToLocal-v0", renderer="babyai-text@1", model="tiny",
                            model_fingerprint=fingerprint_hash(lm.fingerprint), history_len=2)
    sums, counts, neutral = score_records(lm, builder, states.records, batch_size=4)
    annotator = Annotator(lm, None, model="tiny", tasks=("action",), history_len=2, batch_size=4)
    assert annotator.builder("BabyAI-GoToLocal-v0", "babyai-text@1") == builder
    rows = annotator.annotate([[Job(builder.task_key("action", r), builder.render("action", r), builder, r)]
                               for r in states.records])
    assert sums.shape == (12, 3)
    np.testing.assert_allclose(sums, [r["cand_logprob_sum"] for r in rows], rtol=1e-5, atol=1e-5)
    assert counts.tolist() == [r["cand_token_count"] for r in rows]
    np.testing.assert_allclose(neutral, [r["neutral_logprob_sum"] for r in rows], rtol=1e-5, atol=1e-5)


@pytest.mark.usefixtures("model_cache_in_tmp")
def test_probe_on_a_tiny_transformers_model(tiny_lm):
    out = runner.invoke(app, ["probe", "--model", tiny_lm.spec.path, "--dtype", "float32", "--states", "20",
                              "--json"])
    assert out.exit_code == 0, out.output
    figures = json.loads(out.output)
    assert figures["states"] == 20 and figures["config"]["backend"] == "transformers"
    for c in figures["calibrations"].values():
        assert 0.0 <= c["agreement"] <= 1.0 and 0.0 <= c["auroc"] <= 1.0 and c["log_loss"] > 0
        assert 0.0 <= c["mutual_information_bits"] <= np.log2(3) + 1e-9
