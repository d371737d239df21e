"""`illm probe`: the metrics on hand-made rankings with known answers, the bot's states, the
command on the stub backend, and a level without an expert refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.probe import (agreement, expert_states, log_loss, mutual_information_bits, pairwise_auroc,
                              top_choice_entropy_bits)

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


def test_the_bots_states_are_seeded_and_labelled_with_valid_actions():
    a = expert_states("BabyAI-GoToLocal-v0", 40, history=1, seed=3)
    b = expert_states("BabyAI-GoToLocal-v0", 40, history=1, seed=3)
    assert a.records == b.records and a.expert.tolist() == b.expert.tolist() and len(a.records) == 40
    assert a.actions == ("turn left", "turn right", "go forward")  # GoTo levels: the original 3 actions
    assert set(a.expert.tolist()) <= {0, 1, 2} and all(len(r.history) <= 1 for r in a.records)
    assert a.records != expert_states("BabyAI-GoToLocal-v0", 40, history=1, seed=4).records
    greedy = expert_states("BabyAI-GoToLocal-v0", 200, seed=0, epsilon=0.0)
    assert greedy.episodes > 1  # with no random actions the bot finishes its episodes


def test_probe_prints_its_table_and_json(tmp_path):
    args = ["probe", "--backend", "stub", "--model", "stub:16", "--states", "30", "--out", str(tmp_path / "p.json")]
    out = runner.invoke(app, args)
    assert out.exit_code == 0, out.output
    assert "LLM, pmi" in out.output and "always go forward" in out.output and "reading:" in out.output
    figures = json.loads((tmp_path / "p.json").read_text())
    assert figures["states"] == 30 and set(figures["calibrations"]) == {"sum", "mean", "pmi"}
    assert 0.0 <= figures["calibrations"]["sum"]["auroc"] <= 1.0
    as_json = runner.invoke(app, [*args[:-2], "--json"])
    assert json.loads(as_json.output)["baselines"] == figures["baselines"]


def test_a_level_without_an_expert_is_refused_in_one_line():
    out = runner.invoke(app, ["probe", "--env", "MiniGrid-MultiRoom-N6-v0", "--backend", "stub", "--states", "5"])
    assert out.exit_code == 1 and "has no expert to compare with" in out.output
    assert len(out.output.strip().splitlines()) == 1
