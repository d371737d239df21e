"""The language tasks of paper Table 2 (action, summary, goal, plan), any combination on annotate
and train, each with its own head and bonus; and the seam: a task registered from this file (its
own template folder) is annotated, cached, distilled and paid with no other change."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pytest
import torch

from illm_tools.cache import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.intrinsic.illm import ILLMBonus, summary_disagreement
from illm_tools.rl.checkpoint import load_checkpoint
from illm_tools.rl.config import TrainConfig
from illm_tools.tasks.registry import LANGUAGE_TASKS, LanguageTask, parse_tasks, register_task
from fakes import SHORT_ACTIONS, cli_ok as ok, prompt_builder, state_record

ENV = "BabyAI-GoToLocal-v0"


def test_the_plan_task_asks_d2s_question_and_keys_apart_from_the_others():
    b = prompt_builder(model="m", history_len=1)
    state = state_record(history=[("You see a wall 2 steps left", "turn left")], actions=SHORT_ACTIONS)
    prompt = b.render("plan", state)
    assert prompt.text.startswith("You are an expert player playing BabyAI. The goal is: go to the red ball.\n"
                                  "Recent player's history: \nObservation 0: You see a wall 2 steps left")
    assert "What do you do (include 2-7 actions)?\nPlan:" in prompt.text and prompt.candidates is None
    assert json.loads(b.setup("plan")["decoding"]) == {"method": "greedy", "max_new_tokens": 48}
    keys = b.state_keys(state, ("action", "summary", "goal", "plan"))
    assert len(set(keys)) == 4 and keys[:2] == b.state_keys(state)  # the default two are unchanged
    assert parse_tasks("plan+summary") == parse_tasks(["plan", "summary"]) == ("plan", "summary")
    with pytest.raises(UsageError, match="unknown --tasks riddle: choose any of action,summary,goal,plan"):
        parse_tasks("summary,riddle")


def test_the_bonus_pays_and_distils_each_task_on_its_own_block():
    t, n, d = 4, 2, 3
    g = torch.Generator().manual_seed(0)
    pred, target = torch.randn(t, n, 2 * d, generator=g), torch.randn(t, n, 2 * d, generator=g)
    batch = {"summary": pred, "target_emb": target, "target_probs": torch.zeros(t, n, 3),
             "target_mask": torch.ones(t, n, dtype=torch.bool)}
    bonus = ILLMBonus(n, tasks=("summary", "plan"), task_weights={"plan": 0.25}, beta_hc=0.5)
    assert bonus.weights == {"summary": 0.5, "plan": 0.25}
    logs = bonus.compute_rewards(batch).logs
    assert logs["intrinsic_reward_hc"] == pytest.approx(float(summary_disagreement(pred[..., :d], target[..., :d]).mean()))
    assert logs["intrinsic_reward_plan"] == pytest.approx(float(summary_disagreement(pred[..., d:], target[..., d:]).mean()))
    assert "intrinsic_reward_a" not in logs  # no action task, no f^a, no r^a
    loss, parts = bonus.aux_loss({k: v.reshape(t * n, -1).squeeze(-1) for k, v in batch.items()})
    assert set(parts) == {"distill_summary", "distill_plan"} and float(loss) == pytest.approx(sum(parts.values()))
    assert set(bonus.state_dict()) == {"norm_hc", "norm_plan"}


def test_task_settings_are_checked():
    with pytest.raises(UsageError, match="weight is --beta-hc, not --task-weight"):
        TrainConfig.from_dict({"tasks": ("summary",), "task_weights": {"summary": 1.0}})
    with pytest.raises(UsageError, match="goal is not one of this run's --tasks"):
        TrainConfig.from_dict({"tasks": ("summary", "plan"), "task_weights": {"goal": 0.3}})
    with pytest.raises(UsageError, match="--method rnd has none"):
        TrainConfig.from_dict({"method": "rnd", "tasks": ("plan",)})
    assert TrainConfig.from_dict({"tasks": "goal+plan"}).text_tasks == ("goal", "plan")


@pytest.mark.slow  # 6 s: the fast tier's time is spent
def test_every_task_annotates_and_trains_in_any_combination(tmp_path):
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    ok("collect", "--env", ENV, "--steps", 48, "--num-envs", 2, "--out", traj)
    llm = ["--backend", "stub", "--model", "stub:16", "--history", 0]
    out = ok("annotate", traj, "--cache", ann, *llm, "--tasks", "action,summary,goal,plan", "--limit", 5)
    assert "annotated 5 states (20 rows: action 5, goal 5, plan 5, summary 5)" in out
    assert AnnotationCache(ann).tasks() == {"action": 5, "summary": 5, "goal": 5, "plan": 5}
    rows = pa.concat_tables(pa.ipc.open_stream(p.read_bytes()).read_all() for p in sorted(ann.glob("shard-*")))
    for row in rows.to_pylist():  # every text task keeps its text and embedding; the goal task its parsed goals
        if row["task"] != "action":
            assert row["text"] and len(row["embedding"]) == row["embedding_dim"] == 16
        assert (row["candidates"] is not None) == (row["task"] in ("action", "goal"))
    run = tmp_path / "run"
    ok("train", "--env", ENV, "--method", "illm", "--cache", ann, *llm, "--tasks", "summary,plan",
       "--task-weight", "plan=0.3", "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-mode", "sync",
       "--live-budget", 8, "--out", run)
    last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    assert {"charts/intrinsic_reward_hc", "charts/intrinsic_reward_plan"} <= set(last)
    assert "charts/intrinsic_reward_a" not in last and last["charts/target_coverage"] > 0
    weights = load_checkpoint(run)["model"]
    assert "f_plan.2.weight" in weights and "f_hc.2.weight" in weights and "f_a.2.weight" not in weights
    assert weights["f_plan.2.weight"].shape[0] == 16
    ok("train", "--out", run, "--resume", "--frames", 64)  # resumes with its own tasks
    (result,) = json.loads(ok("eval", run, "--episodes", 1, "--json"))
    assert result["episodes"] == 1


@pytest.fixture
def hint_task(tmp_path):
    """A fifth task, defined here: one new entry and its template, nothing else."""
    folder = tmp_path / "templates"
    folder.mkdir()
    (folder / "hint.txt").write_text("You are an expert player playing {task}\nRecent player's history: {history}\n"
                                     "Give the player one hint.\nHint:\n")
    task = register_task(LanguageTask("hint", "text", {"shared": ("hint", 1), "paper": ("hint", 1)},
                                      max_new_tokens=12, template_dir=str(folder), description="a hint"))
    yield task
    LANGUAGE_TASKS.pop("hint")


def test_a_task_registered_from_the_test_file_runs_through_annotate_and_train(tmp_path, hint_task):
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    ok("collect", "--env", ENV, "--steps", 32, "--num-envs", 2, "--out", traj)
    llm = ["--backend", "stub", "--model", "stub:8", "--history", 0]
    ok("annotate", traj, "--cache", ann, *llm, "--tasks", "action,hint", "--limit", 4)
    assert AnnotationCache(ann).tasks() == {"action": 4, "hint": 4}
    run = tmp_path / "run"
    ok("train", "--env", ENV, "--method", "illm", "--cache", ann, *llm, "--tasks", "action,hint",
       "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-mode", "sync", "--live-budget", 8, "--out", run)
    last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    assert {"charts/intrinsic_reward_a", "charts/intrinsic_reward_hint"} <= set(last)
    assert "f_hint.2.weight" in load_checkpoint(run)["model"]
    assert np.isfinite(last["charts/intrinsic_reward_hint"])


def test_hop_mode_asks_every_task_with_the_translated_window(tmp_path):
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    ok("collect", "--env", "MiniGrid-MultiRoom-N6-v0", "--steps", 32, "--num-envs", 2, "--out", traj)
    llm = ["--backend", "stub", "--model", "stub:16", "--history", 0, "--mode", "hop"]
    ok("annotate", traj, "--cache", ann, *llm, "--tasks", "action,summary,goal,plan", "--limit", 3)
    assert AnnotationCache(ann).tasks() == {"action": 3, "summary": 3, "goal": 3, "plan": 3}
    ok("train", "--env", "MiniGrid-MultiRoom-N6-v0", "--method", "illm", "--cache", ann, *llm, "--tasks", "goal+plan",
       "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", 0, "--out", tmp_path / "run")
