"""Crafter in `illm report`: a window's score is the score of its episodes pooled, and each achievement's
success rate per configuration is in report.md and results.json (`illm_tools.report.achievements`)."""
from __future__ import annotations

import json

import pytest

from fakes import fake_run
from illm_tools.envs.crafter_text import ACHIEVEMENTS, crafter_score
from illm_tools.report.build import build_report


def _crafter_run(path, seed, updates):
    """A Crafter run folder: metrics.csv as fake_run writes it, metrics.jsonl with each update's
    achievement rates as the trainer logs them (`charts/achievement_NAME` beside `charts/episodes`)."""
    fake_run(path, seed, [(step, 0.0, episodes) for step, episodes, _ in updates], env_id="CrafterReward-v1")
    with open(path / "metrics.jsonl", "w") as fh:
        for step, episodes, unlocked in updates:
            row = {"global_step": step, "charts/episodes": episodes}
            if episodes:
                row |= {f"charts/achievement_{n}": unlocked.get(n, 0.0) for n in ACHIEVEMENTS}
            fh.write(json.dumps(row) + "\n")


def test_a_window_scores_its_episodes_pooled_and_the_report_lists_each_achievement(tmp_path):
    # seed 0: one window of two updates, 2 episodes that all collected wood, then 2 that none did
    _crafter_run(tmp_path / "a", 0, [(50, 2, {"collect_wood": 1.0}), (100, 2, {"collect_wood": 0.0})])
    _crafter_run(tmp_path / "b", 1, [(50, 0, {}), (100, 4, {"collect_wood": 0.25, "place_table": 0.5})])
    results = build_report([tmp_path / "a", tmp_path / "b"], tmp_path / "out", every=100)
    (row,) = results["rows"]
    pooled = {n: 0.0 for n in ACHIEVEMENTS}
    expected_a = crafter_score(pooled | {"collect_wood": 50.0})
    assert [s["score"] for s in row["final"]["per_seed"]] == pytest.approx(
        [expected_a, crafter_score(pooled | {"collect_wood": 25.0, "place_table": 50.0})])
    # the mean of the two updates' own scores is another number: the pooled one is the paper's
    assert expected_a != pytest.approx((crafter_score(pooled | {"collect_wood": 100.0}) + 0.0) / 2)
    rates = {s["seed"]: s["rates"] for s in row["achievements"]["per_seed"]}
    assert rates[0]["collect_wood"] == 0.5 and rates[1]["place_table"] == 0.5
    assert row["achievements"]["mean"]["collect_wood"] == pytest.approx(0.375)
    report = (tmp_path / "out" / "report.md").read_text()
    assert "| collect_wood | 37.5 |" in report and "| place_table | 25.0 |" in report


def test_a_suite_without_achievements_has_none_in_its_rows(tmp_path):
    fake_run(tmp_path / "a", 0, [(100, 1.0, 1)])
    (row,) = build_report([tmp_path / "a"], tmp_path / "out", every=100)["rows"]
    assert row["achievements"] is None
    assert "achievement" not in (tmp_path / "out" / "report.md").read_text()


def test_a_part_whose_achievements_are_damaged_is_refused_in_one_line(tmp_path):
    from illm_tools.errors import DamagedFileError
    from illm_tools.report.results import read_results

    _crafter_run(tmp_path / "a", 0, [(100, 2, {"collect_wood": 1.0})])
    build_report([tmp_path / "a"], tmp_path / "out", every=100)
    path = tmp_path / "out" / "results.json"
    results = json.loads(path.read_text())
    results["rows"][0]["achievements"]["mean"]["collect_wood"] = "most"
    path.write_text(json.dumps(results))
    with pytest.raises(DamagedFileError, match=r"rows\[0\]\.achievements\.mean"):
        read_results(tmp_path / "out", "--redraw")
