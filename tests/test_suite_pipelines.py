"""Every stage on every suite through the command line, small: collect, annotate (text suites, a
tiny random model), train (illm from the cache on the text suites; ppo and rnd everywhere), eval
with the suite's score; Atari's annotate is refused in one line."""

from __future__ import annotations

import csv
import json

import pytest
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
pytestmark = [pytest.mark.usefixtures("model_cache_in_tmp"), pytest.mark.slow]


def ok(args):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


def scores(run):
    with open(run / "metrics.csv", newline="") as fh:
        return [r["score"] for r in csv.DictReader(fh)]


@pytest.mark.parametrize("env_id,options", [
    ("MiniHack-River-Monster-v0", []),
    ("CrafterReward-v1", ["--env-option", "length=40"]),
])
def test_text_suite_collect_annotate_train_eval(tmp_path, tiny_lm, env_id, options):
    model = tiny_lm.spec.path
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    out = ok(["collect", "--env", env_id, "--steps", 96, "--num-envs", 2, "--out", traj, *options])
    assert "collected 96 steps" in out
    out = ok(["annotate", traj, "--cache", ann, "--model", model, "--dtype", "float32", "--history", 0,
              "--limit", 6, "--batch-size", 3])
    assert "annotated 6 states (12 rows" in out
    common = ["--env", env_id, "--num-envs", 2, "--num-steps", 32, "--frames", 128, "--seed", 0, *options]
    ok(["train", *common, "--method", "illm", "--cache", ann, "--model", model, "--dtype", "float32",
        "--history", 0, "--live-budget", 2, "--live-mode", "sync", "--out", tmp_path / "illm"])
    ok(["train", *common, "--method", "rnd", "--out", tmp_path / "rnd"])
    info = json.loads(ok(["cache", "info", ann, "--json"]))
    assert info["tasks"]["action"] >= 6  # the live fallback wrote its answers back
    (result,) = json.loads(ok(["eval", tmp_path / "illm", "--episodes", 2, "--json"]))
    assert result["env_id"] == env_id and result["episodes"] == 2 and result["score"] == result["score"]


def test_atari_collect_train_eval_and_annotate_refused(tmp_path):
    env_id = "ALE/MontezumaRevenge-v5"
    traj = tmp_path / "traj"
    ok(["collect", "--env", env_id, "--steps", 64, "--num-envs", 2, "--out", traj])
    info = json.loads(ok(["data", "info", traj, "--json"]))
    assert info["rows"] == 64 and info["env_ids"] == [env_id]
    refused = runner.invoke(app, ["annotate", str(traj), "--cache", str(tmp_path / "ann")])
    assert refused.exit_code == 1 and "no text observation" in refused.output and "Traceback" not in refused.output
    assert not (tmp_path / "ann").exists()
    for method in ("ppo", "rnd"):
        ok(["train", "--env", env_id, "--method", method, "--num-envs", 2, "--num-steps", 32, "--frames", 128,
            "--env-option", "max_num_frames_per_episode=200", "--out", tmp_path / method])
    table = ok(["eval", tmp_path / "ppo", tmp_path / "rnd", "--episodes", 2])
    assert "(mean return)" in table and "| rnd | ALE/MontezumaRevenge-v5 | 128 |" in table
    refused = runner.invoke(app, ["train", "--env", env_id, "--method", "chibit", "--frames", 64, "--out",
                                  str(tmp_path / "chibit")])
    assert refused.exit_code == 1 and "reads grid observations" in refused.output


def test_multiroom_collect_and_train(tmp_path):
    ok(["collect", "--env", "MiniGrid-MultiRoom-N6-v0", "--steps", 64, "--num-envs", 2, "--out", tmp_path / "traj"])
    ok(["train", "--env", "MiniGrid-MultiRoom-N6-v0", "--method", "ppo", "--num-envs", 2, "--num-steps", 32,
        "--frames", 128, "--out", tmp_path / "ppo"])
    assert len(scores(tmp_path / "ppo")) == 2
