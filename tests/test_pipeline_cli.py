"""The whole job through the command line on a tiny random model: collect, annotate, cache
info/verify (a damaged shard is named and refused), train illm with the live fallback and ppo,
resume, eval, report."""

from __future__ import annotations

import csv
import json

import pytest
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
REQUIRED = {"global_step", "episodic_return", "success_rate", "sps", "intrinsic_reward_a", "intrinsic_reward_hc",
            "cache_hit_rate", "target_coverage", "live_annotations"}


def ok(args):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")


@pytest.mark.slow
def test_collect_annotate_train_eval_report(tmp_path, tiny_lm):
    model = tiny_lm.spec.path
    traj, ann, runs = tmp_path / "traj", tmp_path / "ann", tmp_path / "runs"
    ok(["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", 64, "--num-envs", 4, "--out", traj])
    out = ok(["annotate", traj, "--cache", ann, "--model", model, "--dtype", "float32", "--limit", 10, "--batch-size", 4])
    assert "annotated 10 states (20 rows" in out
    info = json.loads(ok(["cache", "info", ann, "--json"]))
    assert info["tasks"] == {"action": 10, "summary": 10} and info["embedding_dims"] == [tiny_lm.hidden_size]
    assert ok(["cache", "verify", ann]).strip().endswith("ok")

    train = ["train", "--env", "BabyAI-GoToLocal-v0", "--cache", ann, "--model", model, "--dtype", "float32",
             "--num-envs", 4, "--num-steps", 32, "--live-budget", 4, "--live-mode", "sync", "--seed", 0]
    ok([*train, "--method", "illm", "--frames", 256, "--out", runs / "illm"])
    with open(runs / "illm" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert REQUIRED <= set(rows[0]) and len(rows) == 2
    assert [float(r["live_annotations"]) for r in rows] == [4, 4]  # per rollout, written back to the shared cache
    assert json.loads(ok(["cache", "info", ann, "--json"]))["tasks"]["summary"] == 18
    ok([*train, "--method", "illm", "--frames", 384, "--out", runs / "illm", "--resume"])
    with open(runs / "illm" / "metrics.csv", newline="") as fh:
        assert [int(r["global_step"]) for r in csv.DictReader(fh)] == [128, 256, 384]
    ok(["train", "--method", "ppo", "--frames", 256, "--num-envs", 4, "--num-steps", 32, "--out", runs / "ppo"])

    out = ok(["collect", "--env", "BabyAI-GoToLocal-v0", "--policy", runs / "ppo", "--steps", 32, "--num-envs", 4,
              "--out", tmp_path / "traj-ppo"])
    assert "with policy run:ppo@256" in out

    (result,) = json.loads(ok(["eval", runs / "illm", "--episodes", 4, "--json"]))
    assert result["episodes"] == 4 and 0.0 <= result["success_rate"] <= 1.0
    table = ok(["eval", runs / "illm", runs / "ppo", "--episodes", 2])
    assert "| ppo | BabyAI-GoToLocal-v0 | 256 |" in table and "actions sampled" in table
    assert len({line.count("|") for line in table.splitlines() if line.startswith("|")}) == 1
    assert len(json.loads(ok(["eval", runs / "ppo", runs / "illm", "--episodes", 2, "--json", "--greedy"]))) == 2
    table = ok(["report", runs / "illm", runs / "ppo", "--every", 128])
    assert "| illm |" in table and "| ppo |" in table


def test_a_damaged_shard_is_named_and_refused(tmp_path, tiny_lm):
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    ok(["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", 16, "--num-envs", 2, "--out", traj])
    ok(["annotate", traj, "--cache", ann, "--model", tiny_lm.spec.path, "--dtype", "float32", "--limit", 2,
        "--tasks", "action"])
    shard = next(ann.glob("shard-*.arrow"))
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    result = runner.invoke(app, ["cache", "verify", str(ann)])
    assert result.exit_code == 1 and shard.name in result.output
    result = runner.invoke(app, ["cache", "info", str(ann)])
    assert result.exit_code == 1 and "illm cache verify" in result.output


def test_train_without_a_cache_says_what_to_do(tmp_path):
    result = runner.invoke(app, ["train", "--method", "illm", "--frames", 128, "--out", str(tmp_path / "r")])
    assert result.exit_code == 1 and "--cache" in result.output
