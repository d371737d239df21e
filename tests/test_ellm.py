"""ELLM: the `goal` task (paper D.2 prompt, versioned key, parsing), BabyAI transition captions
(snapshot, and the view-change and rule-based readings agree), the bonus (paid once per goal and
episode, nothing without goals, reaches the advantages), `illm annotate --tasks goal` and
`illm train --method ellm` end to end.

Caption snapshots live in tests/snapshots/babyai_captions.json: per level and seed, the BabyAI
expert bot's actions and the caption of every step. A mismatch means a caption changed: bump
CAPTIONER_VERSION in illm_tools/envs/captions.py, then regenerate with
`ILLM_UPDATE_SNAPSHOTS=1 .venv/bin/pytest tests/test_ellm.py -k snapshot`.
"""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import torch
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX
from typer.testing import CliRunner

from cli.main import app
from illm_tools.envs import make_env
from illm_tools.envs.babyai import ACTION_SPACES
from illm_tools.envs.captions import ACTION_NAMES, CAPTIONER_VERSION, NOTHING, caption
from illm_tools.intrinsic import BonusContext, Targets
from illm_tools.intrinsic.ellm import ELLMBonus, ELLMConfig
from illm_tools.intrinsic.registry import get_method
from illm_tools.tasks.goals import parse_goals
from illm_tools.tasks.registry import LANGUAGE_TASKS
from fakes import cli_ok as ok, prompt_builder as builder, state_record

SNAPSHOTS = Path(__file__).parent / "snapshots" / "babyai_captions.json"
CASES = [("BabyAI-PickupLoc-v0", 2), ("BabyAI-OpenDoor-v0", 3), ("BabyAI-UnlockLocal-v0", 1)]
ENV = "BabyAI-GoToLocal-v0"
ACTIONS = ACTION_SPACES["augmented"]
runner = CliRunner()


# ---- the goal task ---------------------------------------------------------------------------
STATE = state_record(history=[("You see a wall 2 steps forward", "turn left")])
"""A state one step in, of the augmented actions: what the goal task's prompt and keys are checked on."""


def test_goal_prompt_is_the_papers_d2_prompt_in_both_layouts():
    p = builder().render("goal", STATE)
    assert p.text.startswith("You are an expert player playing BabyAI. The goal is: go to the red ball.\n"
                             "Recent player's history: \nObservation 0: You see a wall 2 steps forward\n")
    assert ("Suggest the next goal to reach based on the things you see and previous actions. A goal should "
            "either be a single valid word or a phrase. Only make suggestions that are reasonable given the "
            "current scene (e.g. only \"Open door\" if a door is visible). Prioritize goals that involve the "
            "object you are facing or that the agent has not achieved before.\nGoals:") in p.text
    assert p.text.endswith("\nGoals:") and p.candidates is None
    paper = builder(layout="paper")
    assert paper.render("goal", STATE).text == p.text
    assert paper.task_key("goal", STATE) == builder().task_key("goal", STATE)  # one goal row for both


def test_goal_keys_carry_the_template_and_parser_versions(monkeypatch):
    b = builder()
    key = b.task_key("goal", STATE)
    assert key not in b.state_keys(STATE) and key == builder().task_key("goal", STATE)
    assert b.setup("goal")["decoding"] == ('{"embedding":"mean-last-hidden@1","max_new_tokens":32,"method":"greedy",'
                                          '"parse":"goals@1"}')
    assert builder().task_key("goal", state_record("You see a blue key 1 step forward", STATE.history)) != key
    goal = LANGUAGE_TASKS["goal"]
    monkeypatch.setitem(LANGUAGE_TASKS, "goal", dataclasses.replace(goal, templates={**goal.templates,
                                                                                      "shared": ("goal", 2)}))
    assert builder().setup("goal")["template_version"] == 2 and builder().task_key("goal", STATE) != key
    monkeypatch.undo()
    monkeypatch.setitem(LANGUAGE_TASKS, "goal", dataclasses.replace(goal, decoding_extra={
        **goal.decoding_extra, "parse": "goals@2"}))
    assert builder().task_key("goal", STATE) != key
    monkeypatch.undo()
    assert builder().task_key("goal", STATE) == key


@pytest.mark.parametrize("text,goals", [
    (" go to the red ball, pick up the blue key.\n\nYou are an expert player",
     ["go to the red ball", "pick up the blue key"]),
    ("\n1. Open door\n2) \"Pick up the key\".\n- go to the ball!\nObservation 0: You see a wall",
     ["open door", "pick up the key", "go to the ball"]),
    (" 1. go to the red ball 2. open the door; Goal: explore", ["go to the red ball", "open the door", "explore"]),
    (" You see a red ball 1 step forward, go forward, GO FORWARD, 12, "
     "this item is far too long to be a single word or a phrase", ["go forward"]),
    (" toggle\nRecent player's history: pick up", ["toggle"]),
    ("", []),
    (" a, b, c, d, e, f, g, h, i, j", ["a", "b", "c", "d", "e", "f", "g", "h"]),
])
def test_goal_lists_are_parsed(text, goals):
    assert parse_goals(text) == goals


def test_a_truncated_generation_loses_its_unfinished_last_goal():
    assert parse_goals("\n- Open door\n- Pick up the key\n- Open", truncated=True) == ["open door", "pick up the key"]
    assert parse_goals("\n- Open door\n- Open", truncated=False) == ["open door", "open"]
    assert parse_goals(" go to the ball\n\nThe", truncated=True) == ["go to the ball"]  # the list had ended


# ---- captions --------------------------------------------------------------------------------

def _bot_captions(env_id: str, seed: int) -> dict:
    from minigrid.utils.baby_ai_bot import BabyAIBot

    env = make_env(env_id, action_space="augmented", render_text=False)  # the bot's indices are MiniGrid's
    obs, _ = env.reset(seed=seed)
    bot, actions, captions = BabyAIBot(env.unwrapped), [], []
    for _ in range(64):
        actions.append(int(bot.replan()))
        before = obs["image"]
        obs, _, terminated, truncated, _ = env.step(actions[-1])
        captions.append(caption(before, ACTIONS[actions[-1]], obs["image"]))
        assert caption(before, ACTIONS[actions[-1]], None) == captions[-1]  # the rules predict the change
        if terminated or truncated:
            break
    return {"actions": [ACTIONS[a] for a in actions], "captions": captions, "captioner_version": CAPTIONER_VERSION}


@pytest.mark.parametrize("env_id,seed", CASES)
def test_caption_snapshot(env_id, seed):
    if os.environ.get("ILLM_UPDATE_SNAPSHOTS"):
        data = json.loads(SNAPSHOTS.read_text()) if SNAPSHOTS.exists() else {}
        data[f"{env_id}/{seed}"] = _bot_captions(env_id, seed)
        SNAPSHOTS.write_text(json.dumps(data, indent=1) + "\n")
    case = json.loads(SNAPSHOTS.read_text())[f"{env_id}/{seed}"]
    assert case["captioner_version"] == CAPTIONER_VERSION, "snapshot of another captioner version: regenerate"
    assert _bot_captions(env_id, seed) == case


def view(front=("empty", "grey", "open"), held=None) -> np.ndarray:
    """A 7x7 view of empty floor with `front` in front of the agent and `held` carried."""
    image = np.zeros((7, 7, 3), np.uint8)
    image[:, :, 0] = OBJECT_TO_IDX["empty"]

    def cell(obj, colour, state="open"):
        return [OBJECT_TO_IDX[obj], COLOR_TO_IDX[colour], STATE_TO_IDX[state]]

    image[3, 5] = cell(*front)
    if held is not None:
        image[3, 6] = cell(*held)
    return image


def test_captions_of_hand_built_transitions():
    ball, key, door = ("ball", "red"), ("key", "blue"), ("door", "yellow", "closed")
    assert caption(view(front=ball), "pick up", view(held=ball)) == "you picked up the red ball"
    assert caption(view(held=key), "drop", view(front=key)) == "you dropped the blue key"
    assert caption(view(front=door), "toggle", view(front=("door", "yellow", "open"))) == "you opened the yellow door"
    assert caption(view(front=("door", "yellow", "open")), "toggle", None) == "you closed the yellow door"
    assert caption(view(front=("door", "yellow", "locked"), held=("key", "yellow")), "toggle", None) == \
        "you opened the yellow door"
    assert caption(view(front=("door", "yellow", "locked"), held=key), "toggle", None) == NOTHING  # wrong key
    assert caption(view(front=("box", "green")), "toggle", view()) == "you opened the green box"
    assert caption(view(), "go forward", view()) == "you went forward"
    assert caption(view(front=("wall", "grey")), "go forward", None) == NOTHING
    assert [caption(view(), a) for a in ("turn left", "turn right", "sleep", "pick up", "drop")] == \
        ["you turned left", "you turned right", NOTHING, NOTHING, NOTHING]
    assert ACTION_SPACES["original"] == ACTION_NAMES[:3] and ACTIONS == ACTION_NAMES[:6]  # indices name actions


def test_the_view_change_and_the_rules_agree_on_random_steps():
    seen = set()
    for env_id in ("BabyAI-UnlockLocal-v0", "BabyAI-KeyInBox-v0"):
        env, rng = make_env(env_id, action_space="augmented", render_text=False), np.random.default_rng(0)
        obs, _ = env.reset(seed=0)
        for t in range(2000):
            a = int(rng.integers(len(ACTIONS)))
            before = obs["image"]
            obs, _, terminated, truncated, _ = env.step(a)
            c = caption(before, ACTIONS[a], obs["image"])
            assert caption(before, ACTIONS[a], None) == c, (env_id, t, ACTIONS[a])
            seen.add(c.split(" the ")[0])
            if terminated or truncated:
                obs, _ = env.reset(seed=t + 1)
    assert {"you picked up", "you dropped", "you opened", "you went forward", NOTHING} <= seen


# ---- the bonus -------------------------------------------------------------------------------

MEANING = {"you picked up the red ball": "pickup red ball", "pick up the red ball": "pickup red ball",
           "you turned left": "left", "turn left": "left"}


class FakeEmbedder:
    """Unit vectors equal for texts of one meaning (MEANING), orthogonal otherwise."""

    def __init__(self):
        self.index: dict[str, int] = {}

    def encode(self, texts):
        out = np.zeros((len(texts), 64), np.float32)
        for row, text in enumerate(texts):
            out[row, self.index.setdefault(MEANING.get(text, text), len(self.index))] = 1.0
        return out


class FakeGoals:
    """A goal provider: `goals_of(record index)` per step; `targets` answers only the mask."""

    def __init__(self, goals_of, num_actions=6):
        self.goals_of, self.num_actions, self.goals = goals_of, num_actions, []

    def targets(self, records):
        self.goals = [self.goals_of(k) for k in range(len(records))]
        mask = np.array([g is not None for g in self.goals])
        b = len(records)
        return Targets(np.zeros((b, self.num_actions), np.float32), np.zeros((b, 0), np.float32), mask)

    def stats(self):
        return {}


def bonus(**kw) -> ELLMBonus:
    ctx = BonusContext(num_envs=2, num_steps=4, image_shape=(7, 7, 3), num_actions=6, feature_dim=8,
                       int_gamma=0.99, seed=0)
    return ELLMBonus(ELLMConfig(**kw), ctx, embedder=FakeEmbedder())


def rollout(steps, provider) -> dict:
    """A [T, 2] batch from per-step (env 0, env 1) transitions (before, action index, after, end);
    the provider answers for its T * 2 records first, as the trainer asks before the bonus."""
    t = len(steps)
    flat = [tr for pair in steps for tr in pair]
    mask = provider.targets([None] * len(flat)).mask
    return {"images": torch.as_tensor(np.stack([tr[0] for tr in flat])).view(t, 2, 7, 7, 3),
            "actions": torch.tensor([tr[1] for tr in flat]).view(t, 2),
            "next_images": torch.as_tensor(np.stack([tr[2] for tr in flat])).view(t, 2, 7, 7, 3),
            "ends": torch.tensor([float(tr[3]) for tr in flat]).view(t, 2),
            "target_mask": torch.as_tensor(mask).view(t, 2)}


BALL = ("ball", "red")
PICK = (view(front=BALL), 3, view(held=BALL), False)   # "you picked up the red ball"
DROP = (view(held=BALL), 4, view(front=BALL), False)   # "you dropped the red ball"
LEFT = (view(), 0, view(), False)                      # "you turned left"


def test_a_goal_is_paid_once_per_episode():
    provider = FakeGoals(lambda k: ("pick up the red ball", "open the door"))
    b = bonus()
    b.use_provider(provider)
    # env 0: picks up, drops, picks up again (same episode), picks up after its episode ended
    end_pick = PICK[:3] + (True,)
    out = b.compute_rewards(rollout([(PICK, LEFT), (DROP, LEFT), (end_pick, LEFT), (PICK, LEFT)], provider))
    assert out.reward[:, 0].tolist() == [1.0, 0.0, 0.0, 1.0]  # paid again only in the next episode
    assert out.reward[:, 1].tolist() == [0.0] * 4  # "turn left" was not suggested
    assert out.logs["ellm_goals_achieved"] == 2 and out.logs["target_coverage"] == 1.0
    # the set carries over rollouts: env 0's episode is still the one that achieved the goal
    again = b.compute_rewards(rollout([(PICK, LEFT)], provider))
    assert again.reward.tolist() == [[0.0, 0.0]]


def test_a_state_without_goals_gets_nothing_and_is_counted():
    provider = FakeGoals(lambda k: None if k % 2 == 0 else ("turn left",))  # env 0: no goal row; env 1: a goal
    b = bonus()
    b.use_provider(provider)
    out = b.compute_rewards(rollout([(PICK, LEFT), (PICK, LEFT)], provider))
    assert out.reward[:, 0].tolist() == [0.0, 0.0] and out.reward[:, 1].tolist() == [1.0, 0.0]
    assert out.logs["no_target_steps"] == 2 and out.logs["target_coverage"] == 0.5
    provider = FakeGoals(lambda k: ())  # rows with no parsable goal
    b.use_provider(provider)
    out = b.compute_rewards(rollout([(PICK, LEFT)], provider))
    assert not out.reward.any() and out.logs["goal_empty_steps"] == 2 and out.logs["no_target_steps"] == 0


def test_threshold_coef_and_options():
    provider = FakeGoals(lambda k: ("pick up the red ball",))
    b = bonus(coef=0.5)
    b.use_provider(provider)
    assert b.compute_rewards(rollout([(PICK, PICK)], provider)).reward.tolist() == [[0.5, 0.5]]
    method = get_method("ellm")
    assert method.needs_targets and not method.policy_heads and method.target_tasks == ("goal",)
    assert method.parse_options(["threshold=0.85", "normalize=true"]) == {"threshold": 0.85, "normalize": True}
    with pytest.raises(Exception, match="threshold"):
        ELLMConfig(threshold=1.5)
    with pytest.raises(Exception, match="goal provider"):
        bonus().compute_rewards(rollout([(PICK, PICK)], provider))


def test_the_ellm_bonus_reaches_the_advantages(tmp_path):
    from illm_tools.rl import TrainConfig, Trainer
    from fakes import FakePool

    cfg = TrainConfig.from_dict(dict(run_dir=tmp_path / "run", method="ellm", num_envs=4, num_steps=32, total_steps=4 * 32,
                      tensorboard=False, update_epochs=1, num_minibatches=2, int_gamma=0.9))
    provider = FakeGoals(lambda k: ("turn left",) if k % 5 else None)
    trainer = Trainer(cfg.resolved(), FakePool(cfg.num_envs), provider)  # hands the bonus its provider
    assert trainer.bonus.provider is provider
    trainer.bonus.embedder = FakeEmbedder()
    ro, records, _, next_values = trainer.collect_rollout()
    assert len(records) == 128  # the trainer builds records for a bonus that needs targets
    trainer.attach_targets(ro, records)
    out = trainer.intrinsic_rewards(ro)
    assert (out.reward > 0).any() and out.logs["target_coverage"] < 1.0
    with_bonus = trainer.advantages(ro, out.reward, next_values).advantages
    without = trainer.advantages(ro, torch.zeros_like(out.reward), next_values).advantages
    assert not torch.allclose(with_bonus, without)


def test_minilm_embeddings_rank_the_fulfilled_goal_first():
    from illm_tools.llm.sentence import shared_embedder

    e = shared_embedder()
    goals = ["pick up the red ball", "open the yellow door", "go to the blue key", "turn left"]
    vectors = e.encode(goals)
    assert vectors.shape == (4, 384) and np.allclose(np.linalg.norm(vectors, axis=1), 1.0, atol=1e-5)
    for k, cap in enumerate(["you picked up the red ball", "you opened the yellow door", "you went to the blue key",
                             "you turned left"]):
        sims = vectors @ e.encode([cap])[0]
        assert sims.argmax() == k and sims[k] > 0.7
    assert np.array_equal(e.encode(["turn left"]), vectors[3:])  # memoised


# ---- end to end ------------------------------------------------------------------------------

@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_annotate_goal_then_train_ellm(tmp_path, tiny_lm, monkeypatch):
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.collect import CollectConfig, collect

    monkeypatch.setenv("ILLM_CACHE_DIR", str(tmp_path / "illm-cache"))
    traj, cache = tmp_path / "traj", tmp_path / "ann"
    collect(CollectConfig(env_id=ENV, out=traj, steps=32, num_envs=4, seed=1))
    annotate = ["annotate", str(traj), "--cache", str(cache), "--model", tiny_lm.spec.path, "--dtype", "float32",
                "--history", "0", "--tasks", "goal", "--batch-size", "4"]
    ok(*annotate)
    ann = AnnotationCache(cache)
    assert ann.tasks() == {"goal": len(ann)} and len(ann) > 0
    table = pa.concat_tables(pa.ipc.open_stream(p.read_bytes()).read_all() for p in sorted(cache.glob("shard-*")))
    rows = table.to_pylist()
    assert all(r["candidates"] in (parse_goals(r["text"]), parse_goals(r["text"], truncated=True)) for r in rows)
    assert all(r["prompt"].endswith("\nGoals:") and json.loads(r["decoding"])["parse"] == "goals@1" for r in rows)
    assert all(len(r["embedding"]) == r["embedding_dim"] == tiny_lm.hidden_size and r["cand_logprob_sum"] is None
               for r in rows)  # the text's embedding: the goal head of iLLM (--tasks goal) learns it
    assert "nothing to annotate" in ok(*annotate)
    assert len(AnnotationCache(cache)) == len(ann)

    run = tmp_path / "run"
    ok("train", "--method", "ellm", "--env", ENV, "--cache", cache, "--model", tiny_lm.spec.path, "--dtype", "float32",
       "--history", 0, "--num-envs", 4, "--num-steps", 32, "--frames", 256, "--live-mode", "sync", "--live-budget", 4,
       "--bonus-option", "threshold=0.5", "--out", run)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and all("charts/ellm_paid_steps" in r and "charts/target_coverage" in r for r in rows)
    assert sum(r["charts/live_annotations"] for r in rows) > 0  # the live fallback annotated goals
    after = AnnotationCache(cache)
    assert after.tasks() == {"goal": len(after)} and len(after) > len(ann)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["method"] == "ellm" and cfg["bonus_options"] == {"threshold": 0.5}
    assert json.loads(ok("eval", run, "--episodes", 2, "--json"))[0]["method"] == "ellm"
    # a goal-only cache has nothing for iLLM, and says how to annotate it
    out = runner.invoke(app, [str(a) for a in [
        "train", "--method", "illm", "--env", ENV, "--cache", cache, "--model", tiny_lm.spec.path, "--dtype", "float32",
        "--history", 0, "--frames", 128, "--out", tmp_path / "illm"]])
    assert out.exit_code == 1 and "--tasks action,summary" in out.output, out.output
