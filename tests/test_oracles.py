"""Oracles as a plug-in kind (`illm_tools/oracles/`): the registry picks a state's oracle by the game
its prompt names and refuses, in one line naming the games that have one, a game none reads; a
third oracle is one file plus one entry: the docs' corridor oracle (docs/examples/corridor_oracle.py,
quoted by docs/extending/oracle.md), found only through an `illm.oracles` entry point, annotates the
docs' corridor suite through `--backend oracle` beside the BabyAI oracle, and a run trains on its
answers, with no edit to illm.
(The BabyAI oracle's answers themselves are pinned by tests/test_oracle_snapshot.py.)"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from fakes import EXAMPLES, cli_ok as ok, plugins_installed
from illm_tools.errors import UsageError
from illm_tools.llm.backend import backend_fingerprint, load_backend
from illm_tools.oracles.base import Oracle, family_of
from illm_tools.oracles.registry import ORACLES, known_families, oracle_for
from illm_tools.tasks.prompts import PromptBuilder, game_of
from illm_tools.tasks.state import StateRecord

ENV = "Corridor-Walk-v0"


def test_each_suite_s_oracle_reads_its_games_and_other_games_are_refused_by_name():
    assert list(ORACLES) == ["babyai", "crafter", "minihack"]
    assert known_families() == ("BabyAI", "MiniGrid", "Crafter", "MiniHack")
    assert oracle_for("BabyAI") == oracle_for("MiniGrid") == "babyai"
    assert oracle_for("MiniHack") == "minihack" and oracle_for("Crafter") == "crafter"
    for env_id in ("ALE/Pong-v5", ENV):
        with pytest.raises(UsageError, match=rf"knows BabyAI, MiniGrid, Crafter and MiniHack only, not {env_id}: use an LLM backend"):
            oracle_for(family_of(env_id), env_id)
    # one rule for the game a prompt names and the oracle that reads it
    for env_id in ("BabyAI-GoToLocal-v0", "MiniGrid-DoorKey-5x5-v0", "MiniHack-Room-5x5-v0", "CrafterReward-v1"):
        assert game_of(env_id) == family_of(env_id)
    assert family_of("CrafterNoReward-v1") == "Crafter" and family_of("MiniHack-Room-5x5-v0") == "MiniHack"


class Twin(Oracle):
    """Claims a game the BabyAI oracle reads."""

    families, version = ("MiniGrid",), "twin@1"

    def costs(self, scene):
        return dict.fromkeys(scene.actions, 0.0)

    def text(self, scene, task):
        return "twin"

    def random_text(self, scene, task, rng):
        return "twin"


def test_a_class_that_is_no_oracle_or_claims_a_read_game_is_refused():
    ORACLES.register("nothing", dict)
    try:
        with pytest.raises(TypeError, match="is not an Oracle subclass"):
            known_families()
    finally:
        del ORACLES["nothing"]
    ORACLES.register("twin", Twin)
    try:
        with pytest.raises(UsageError, match="'babyai' and 'twin' both read MiniGrid"):
            oracle_for("MiniGrid")
    finally:
        del ORACLES["twin"]
    assert oracle_for("MiniGrid") == "babyai"


@pytest.fixture
def corridor(monkeypatch):
    """The docs' corridor suite and its oracle as an installed package's entry points."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    with plugins_installed(monkeypatch, {"illm.suites": [("corridor", "corridor_suite:SUITE")],
                                         "illm.oracles": [("corridor", "corridor_oracle:CorridorOracle")]},
                           also=(ORACLES,)) as added:
        yield added[-1]


def _rows(cache) -> list[dict]:
    from illm_tools.cache import layout

    manifest = json.loads((cache / "manifest.json").read_text())
    return [r for s in manifest["shards"] for r in layout.read_shard(cache / s["name"]).to_pylist()]


def test_an_oracle_plugged_in_annotates_its_suite_through_the_oracle_backend(corridor, tmp_path):
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    ok("collect", "--env", ENV, "--env-option", "length=6", "--steps", 40, "--num-envs", 2, "--out", traj)
    assert corridor == ["corridor"] and known_families() == ("BabyAI", "MiniGrid", "Crafter", "MiniHack", "Corridor")
    assert backend_fingerprint("oracle", "oracle")["revision"] == \
        "planner@1+crafter-planner@1+minihack-planner@1+corridor@1+answers@1"

    said = ok("annotate", traj, "--cache", ann, "--backend", "oracle", "--history", 0, "--tasks",
              "action,summary,goal,plan")
    assert "100% of the 40 steps" in said
    assert "--backend oracle" in ok("cache", "info", ann)
    rows = _rows(ann)
    actions = [r for r in rows if r["task"] == "action"]
    assert len(actions) >= 4  # the distinct states: 1 to 5 steps from the end
    for row in actions:  # "go right" is two steps better than "go left": e^-4 as likely
        assert row["candidates"] == ["go left", "go right"] and row["chosen_index"] == 1
        assert np.isclose(row["cand_logprob_sum"][1] - row["cand_logprob_sum"][0], 4.0)
    summaries = {r["observation"]: r["text"] for r in rows if r["task"] == "summary"}
    for observation, text in summaries.items():
        left = observation.split()[2]
        assert text == f"The agent must reach the end of the corridor. The end is {left} steps to the right."
    plans = {r["text"] for r in rows if r["task"] == "plan"}
    assert len(plans) >= 4 and all(set(p.split(", ")) == {"go right"} for p in plans)
    ok("train", "--env", ENV, "--env-option", "length=6", "--method", "illm", "--cache", ann, "--backend", "oracle",
       "--history", 0, "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--out", tmp_path / "run")
    with open(tmp_path / "run" / "metrics.csv", newline="") as fh:
        assert float(next(csv.DictReader(fh))["target_coverage"]) > 0

    # one backend answers both games, each by its own oracle; a game none reads is still refused
    lm = load_backend("oracle", "oracle")
    for env_id, record, best in ((ENV, StateRecord("reach the end of the corridor", (), "You are 2 steps from the goal",
                                                   ("go left", "go right")), "go right"),
                                 ("BabyAI-GoToLocal-v0", StateRecord("go to the red ball", (),
                                                                     "You see a red ball 2 steps right",
                                                                     ("turn left", "turn right", "go forward")),
                                  "turn right")):
        prompt = PromptBuilder(env_id=env_id, renderer="r@1", model="oracle", model_fingerprint="f",
                               history_len=0).render("action", record)
        assert prompt.candidates[lm.score([prompt.text], [list(prompt.candidates)])[0].best].strip() == best
    with pytest.raises(UsageError, match="knows BabyAI, MiniGrid, Crafter, MiniHack and Corridor only, not ALE/Pong-v5"):
        lm.check_use("ALE/Pong-v5", "atari-frames@1")


def test_without_its_oracle_the_suite_is_refused_by_the_oracle_backend(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(EXAMPLES))
    with plugins_installed(monkeypatch, {"illm.suites": [("corridor", "corridor_suite:SUITE")]}):
        ok("collect", "--env", ENV, "--steps", 8, "--num-envs", 2, "--out", tmp_path / "traj")
        out = CliRunner().invoke(app, ["annotate", str(tmp_path / "traj"), "--cache", str(tmp_path / "ann"),
                                       "--backend", "oracle", "--history", "0"])
    assert out.exit_code == 1 and "Traceback" not in out.output
    assert "the oracle backend knows BabyAI, MiniGrid, Crafter and MiniHack only, not Corridor-Walk-v0" in out.output
    assert not (tmp_path / "ann" / "manifest.json").exists()
