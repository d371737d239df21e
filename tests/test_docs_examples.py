"""The documentation's plug-in examples run: docs/examples/ holds the one-file bonus, suite, backend and
language task that docs/extending/*.md quote (the pages include these files, so what a reader copies is
what runs here). Each is found only through a (fake) entry point of its group, as an installed package
would declare it, and goes through collect, annotate and train with no edit to illm."""

from __future__ import annotations

import csv
import json

import pytest

from fakes import EXAMPLES, cli_ok as ok, plugins_installed
from illm_tools.rl.checkpoint import load_checkpoint

ENV = "Corridor-Walk-v0"
SMALL = ["--num-envs", 2, "--num-steps", 16, "--frames", 32]


@pytest.fixture
def examples(monkeypatch):
    """The four examples as entry points of their groups, as the docs' pyproject snippet declares them."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    points = {
        "illm.methods": [("count", "count_bonus:METHOD")],
        "illm.suites": [("corridor", "corridor_suite:SUITE")],
        "illm.backends": [("keywords", "keyword_backend:KeywordBackend")],
        "illm.tasks": [("hint", "hint_task:TASK")],
    }
    with plugins_installed(monkeypatch, points) as added:
        yield added


def test_the_docs_plugin_examples_collect_annotate_and_train(examples, tmp_path):
    assert examples == [["count"], ["hint"], ["keywords"], ["corridor"]]  # methods, tasks, backends, suites
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    assert ENV in ok("envs", "--ids")

    # the suite: collected with one of its options, trained with a bonus that reads observations
    ok("collect", "--env", ENV, "--env-option", "length=4", "--steps", 48, "--num-envs", 2, "--out", traj)
    ok("train", "--env", ENV, "--method", "rnd", *SMALL, "--out", tmp_path / "rnd")

    # the bonus: its option parsed into its config, its reward reaching the advantages
    ok("train", "--env", ENV, "--method", "count", "--bonus-option", "scale=0.5", *SMALL, "--out", tmp_path / "count")
    with open(tmp_path / "count" / "metrics.csv", newline="") as fh:
        assert float(next(csv.DictReader(fh))["adv_int_abs"]) > 0
    last = json.loads((tmp_path / "count" / "metrics.jsonl").read_text().splitlines()[-1])
    assert last["charts/count_distinct"] >= 1

    # the backend: annotates the suite's states into a cache and gives iLLM its targets
    said = ok("annotate", traj, "--cache", ann, "--backend", "keywords", "--history", 0)
    assert "states" in said
    assert "--backend keywords --model keywords" in ok("cache", "info", ann)
    ok("train", "--env", ENV, "--method", "illm", "--cache", ann, "--backend", "keywords", "--history", 0, *SMALL,
       "--live-budget", "all", "--live-mode", "sync", "--out", tmp_path / "illm")
    with open(tmp_path / "illm" / "metrics.csv", newline="") as fh:
        assert all(float(r["target_coverage"]) == 1.0 for r in csv.DictReader(fh))

    # the task: annotated with the others, a head and a bonus of its own
    ok("annotate", traj, "--cache", ann, "--backend", "keywords", "--history", 0, "--tasks", "action,summary,hint")
    run = tmp_path / "hint"
    ok("train", "--env", ENV, "--method", "illm", "--cache", ann, "--backend", "keywords", "--history", 0,
       "--tasks", "action,summary,hint", "--task-weight", "hint=0.5", *SMALL, "--live-budget", "all",
       "--live-mode", "sync", "--out", run)
    last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    assert "charts/intrinsic_reward_hint" in last and "f_hint.2.weight" in load_checkpoint(run)["model"]
