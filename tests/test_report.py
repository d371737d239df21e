"""`illm report`: curve points are episode-weighted windows, aligned by frame across seeds."""

from __future__ import annotations

import csv
import json

from illm_tools.report.curves import summarise
from illm_tools.rl.checkpoint import CSV_COLUMNS


def fake_run(path, seed, rows):
    path.mkdir()
    (path / "config.json").write_text(json.dumps({"mode": "illm", "env_id": "BabyAI-GoToLocal-v0", "seed": seed}))
    with open(path / "metrics.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for step, success, episodes in rows:
            writer.writerow({"global_step": step, "success_rate": success, "episodes": episodes,
                             "target_coverage": 0.5, "cache_hit_rate": 0.25})


def test_points_are_weighted_windows_aligned_by_frame(tmp_path):
    # run a: 4 updates of 50 frames; run b killed after 2 updates plus a short one at 120
    fake_run(tmp_path / "a", 0, [(50, 1.0, 1), (100, 0.0, 3), (150, 0.5, 2), (200, 0.5, 2)])
    fake_run(tmp_path / "b", 1, [(50, 0.0, 1), (100, 0.0, 1), (120, 1.0, 1)])
    (group,) = summarise([tmp_path / "a", tmp_path / "b"], every=100).values()
    assert group["frames"] == [100]  # b's short window (100, 120] has no partner in a
    assert group["mean"] == [(0.25 + 0.0) / 2]  # a: (1*1 + 0*3) / 4; b: 0
    assert group["coverage"] == 0.5 and group["hit_rate"] == 0.25
    (alone,) = summarise([tmp_path / "b"], every=100).values()
    assert alone["frames"] == [100, 120] and alone["mean"] == [0.0, 1.0]


def test_runs_with_other_bonus_weights_are_reported_apart(tmp_path):
    from illm_tools.report.curves import group_labels

    base = {"mode": "illm", "env_id": "E", "lambda_a": 0.8, "ext_coef": 1.0, "seed": 0, "run_dir": "a"}
    assert group_labels([{**base, "mode": "ppo"}, base]) == ["ppo", "illm"]  # other methods are not compared
    assert group_labels([base, {**base, "ext_coef": 2.0, "seed": 1, "run_dir": "b"}]) == \
        ["illm (ext_coef 1)", "illm (ext_coef 2)"]
    fake_run(tmp_path / "a", 0, [(100, 1.0, 1)])
    fake_run(tmp_path / "b", 0, [(100, 0.0, 1)])
    cfg = json.loads((tmp_path / "b" / "config.json").read_text())
    (tmp_path / "b" / "config.json").write_text(json.dumps({**cfg, "ext_coef": 2.0}))
    groups = summarise([tmp_path / "a", tmp_path / "b"], every=100)
    assert sorted(method for _, method in groups) == ["illm (ext_coef 2)", "illm (ext_coef None)"]


def test_duplicate_seeds_are_refused_and_short_runs_are_named(tmp_path):
    import pytest
    from typer.testing import CliRunner

    from cli.main import app
    from illm_tools.errors import UsageError

    fake_run(tmp_path / "a", 0, [(100, 1.0, 1)])
    fake_run(tmp_path / "copy", 0, [(100, 1.0, 1)])
    with pytest.raises(UsageError, match="same configuration with the same seed 0"):
        summarise([tmp_path / "a", tmp_path / "copy"], every=100)
    fake_run(tmp_path / "short", 1, [(50, 1.0, 1)])
    out = CliRunner().invoke(app, ["report", str(tmp_path / "a"), str(tmp_path / "short"), "--every", "100"])
    assert out.exit_code == 0, out.output
    assert "short left out: trained for 50 frames, too short for a point at --every 100" in out.output
    alone = CliRunner().invoke(app, ["report", str(tmp_path / "short"), "--every", "1000"])  # no run has a point
    assert alone.exit_code == 0 and "short left out" in alone.output, alone.output
    missing = CliRunner().invoke(app, ["report", str(tmp_path / "runs-*"), "--every", "100"])
    assert missing.exit_code == 1 and "no run folder at" in missing.output
    table = [line for line in out.output.splitlines() if line.startswith("|")]
    assert len({line.count("|") for line in table}) == 1  # every row has the header's columns
    assert "| 1 | 1.00 ± 0.00 | 50.0% |" in out.output
