"""The docs' new-level example (docs/examples/goal_level.py, quoted by docs/extending/level.md) runs as the
page says: plugged in through an `illm.suites` entry point, its suite (the babyai suite narrowed to
one id) owns the level and no other suite does, the level's text is BabyAI-Text under the babyai
renderer's name and version, and the oracle, whose env-id rule is the id's family, annotates it for a
run: collect, annotate with the oracle, train."""

from __future__ import annotations

import csv

import gymnasium as gym
import pytest

from fakes import EXAMPLES, cli_ok as ok, plugins_installed
from illm_tools.envs import SUITES, make_env, renderer_of, suite_of
from illm_tools.envs.babyai import render_text
from illm_tools.errors import UsageError
from illm_tools.llm.oracle import OracleBackend

ENV = "MiniGrid-GoalCorner-v0"


@pytest.fixture
def level(monkeypatch):
    """The example as an installed package's `illm.suites` entry point; its gymnasium id dropped after."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    try:
        with plugins_installed(monkeypatch, {"illm.suites": [("goal-corner", "goal_level:SUITE")]}) as added:
            yield added
    finally:
        gym.registry.pop(ENV, None)


def test_the_level_is_owned_by_its_suite_and_reads_as_babyai_text(level):
    assert level[3] == ["goal-corner"]
    ids = ok("envs", "--ids").split()
    assert ids.count(ENV) == 1  # its suite lists it; the babyai suite's listing was taken without it
    suite = suite_of(ENV)
    assert suite.name == "goal-corner" and list(SUITES).index("babyai") < list(SUITES).index("goal-corner")
    assert renderer_of(ENV) == SUITES["babyai"].renderer == "babyai-text@1" and suite.network == "grid-mission"
    env = make_env(ENV)
    obs, info = env.reset(seed=3)
    assert info["mission"] == "get to the green goal square" and info["text"] == render_text(obs["image"])
    assert info["valid_actions"] == ["turn left", "turn right", "go forward", "pick up", "drop", "toggle"]
    # the oracle's rule: an id of the BabyAI or MiniGrid family (the game the prompt names)
    OracleBackend.check_use(ENV, renderer_of(ENV))
    with pytest.raises(UsageError, match="knows BabyAI, MiniGrid, Crafter and MiniHack only"):
        OracleBackend.check_use("GoalCorner-v0", "babyai-text@1")


def test_the_level_collects_annotates_with_the_oracle_and_trains(level, tmp_path):
    traj, ann, run = tmp_path / "traj", tmp_path / "ann", tmp_path / "run"
    ok("collect", "--env", ENV, "--steps", 64, "--num-envs", 2, "--out", traj)
    said = ok("annotate", traj, "--cache", ann, "--backend", "oracle", "--history", 0)
    assert "100% of the 64 steps" in said
    ok("train", "--env", ENV, "--method", "illm", "--cache", ann, "--backend", "oracle", "--history", 0,
       "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--out", run)
    with open(run / "metrics.csv", newline="") as fh:
        assert float(next(csv.DictReader(fh))["target_coverage"]) > 0
