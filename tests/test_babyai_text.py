"""BabyAI-Text renderer (snapshots and hand-built views), action vocabularies and the env registry.

Snapshots live in tests/snapshots/babyai_text.json: per level and seed, the actions of the BabyAI
expert bot and the text after reset and after every step. A mismatch means the rendered text
changed: bump RENDERER_VERSION in illm_tools/envs/babyai.py, then regenerate with
`ILLM_UPDATE_SNAPSHOTS=1 .venv/bin/pytest tests/test_babyai_text.py`.
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX

from illm_tools.envs import known_env_ids, make_env, renderer_of, resolve_action_space
from illm_tools.envs.babyai import ACTION_SPACES, RENDERER_VERSION, describe, render_text
from illm_tools.errors import UnknownEnvError, UsageError

SNAPSHOTS = Path(__file__).parent / "snapshots" / "babyai_text.json"
CASES = [("BabyAI-GoToLocal-v0", 4), ("BabyAI-GoToLocal-v0", 11), ("BabyAI-PickupLoc-v0", 2),
         ("BabyAI-OpenDoor-v0", 3), ("BabyAI-UnlockLocal-v0", 1)]


def _record(env_id: str, seed: int) -> dict:
    from minigrid.utils.baby_ai_bot import BabyAIBot

    env = make_env(env_id, action_space="augmented")  # the bot's action indices are MiniGrid's
    _, info = env.reset(seed=seed)
    bot, actions, texts = BabyAIBot(env.unwrapped), [], [info["text"]]
    for _ in range(64):
        actions.append(int(bot.replan()))
        _, _, terminated, truncated, info = env.step(actions[-1])
        texts.append(info["text"])
        if terminated or truncated:
            break
    return {"env_id": env_id, "seed": seed, "mission": info["mission"], "actions": actions, "texts": texts,
            "renderer_version": RENDERER_VERSION}


def _snapshots() -> dict:
    if os.environ.get("ILLM_UPDATE_SNAPSHOTS"):
        data = {f"{env_id}/{seed}": _record(env_id, seed) for env_id, seed in CASES}
        SNAPSHOTS.parent.mkdir(exist_ok=True)
        SNAPSHOTS.write_text(json.dumps(data, indent=1) + "\n")
    return json.loads(SNAPSHOTS.read_text())


@pytest.mark.parametrize("env_id,seed", CASES)
def test_snapshot(env_id, seed):
    case = _snapshots()[f"{env_id}/{seed}"]
    assert case["renderer_version"] == RENDERER_VERSION, "snapshot of another renderer version: regenerate"
    env = make_env(env_id, action_space="augmented")
    _, info = env.reset(seed=seed)
    texts = [info["text"]]
    for action in case["actions"]:
        _, _, _, _, info = env.step(action)
        texts.append(info["text"])
    assert info["mission"] == case["mission"]
    assert texts == case["texts"], "rendered text changed: bump RENDERER_VERSION and regenerate snapshots"


def test_snapshots_cover_carrying_and_doors():
    texts = " ".join(t for case in _snapshots().values() for t in case["texts"])
    for phrase in ("You carry a", "locked", "closed", "an open", "You see a wall"):
        assert phrase in texts


def _view(*cells, carry=None):
    """A 7x7 view of empty cells with (x, y, object, colour, state) cells; the agent is at (3, 6)."""
    image = np.zeros((7, 7, 3), dtype=np.uint8)
    image[:, :, 0] = OBJECT_TO_IDX["empty"]
    for x, y, obj, colour, state in cells:
        image[x, y] = (OBJECT_TO_IDX[obj], COLOR_TO_IDX[colour], STATE_TO_IDX.get(state, 0))
    if carry:
        image[3, 6] = (OBJECT_TO_IDX[carry[1]], COLOR_TO_IDX[carry[0]], 0)
    return image


def test_object_location_sentences():
    image = _view((1, 5, "ball", "red", ""), (3, 5, "key", "green", ""), (4, 6, "box", "purple", ""),
                  (6, 2, "ball", "grey", ""))
    assert describe(image) == [
        "You see a red ball 2 steps left and 1 step forward",
        "You see a green key 1 step forward",
        "You see a purple box 1 step right",
        "You see a grey ball 3 steps right and 4 steps forward",
    ]


def test_door_states():
    image = _view((6, 4, "door", "yellow", "closed"), (0, 4, "door", "red", "open"),
                  (3, 1, "door", "blue", "locked"))
    assert describe(image) == [
        "You see an open red door 3 steps left and 2 steps forward",
        "You see a locked blue door 5 steps forward",
        "You see a closed yellow door 3 steps right and 2 steps forward",
    ]


def test_walls_ahead_left_right_only():
    image = _view(*[(x, 4, "wall", "grey", "") for x in range(7)], (0, 6, "wall", "grey", ""),
                  (5, 6, "wall", "grey", ""), (6, 6, "wall", "grey", ""))
    assert describe(image) == ["You see a wall 2 steps forward", "You see a wall 3 steps left",
                               "You see a wall 2 steps right"]


def test_wall_hidden_by_object_or_unseen_cells():
    image = _view((3, 5, "ball", "blue", ""), (3, 2, "wall", "grey", ""), (2, 6, "key", "red", ""),
                  (0, 6, "wall", "grey", ""))
    image[4:, 6, 0] = OBJECT_TO_IDX["unseen"]
    image[6, 6, 0] = OBJECT_TO_IDX["wall"]  # seen through unseen cells, as GLAM does
    assert describe(image) == ["You see a wall 3 steps right", "You see a red key 1 step left",
                               "You see a blue ball 1 step forward"]


def test_a_sentence_made_once_is_not_reused_in_a_view_of_another_size():
    """Each object's sentence is made once per (cell, view size, codes): cell 13 of a 7x7 view and
    of a 5x5 view lie at different places from the agent."""
    image = _view((1, 6, "ball", "red", ""))  # cell 1 * 7 + 6 = 13
    small = np.zeros((5, 5, 3), dtype=np.uint8)
    small[:, :, 0] = OBJECT_TO_IDX["empty"]
    small[2, 3] = image[1, 6]  # cell 2 * 5 + 3 = 13
    for _ in range(2):
        assert describe(image) == ["You see a red ball 2 steps left"]
        assert describe(small) == ["You see a red ball 1 step forward"]


def test_carry_comes_first_and_empty_view():
    image = _view((3, 4, "wall", "grey", ""), carry=("blue", "key"))
    assert render_text(image) == "You carry a blue key, You see a wall 2 steps forward"
    assert render_text(_view()) == ""


@pytest.mark.parametrize("space,size", [("original", 3), ("augmented", 6), ("irrelevant", 9)])
def test_action_space_sizes(space, size):
    env = make_env("BabyAI-GoToLocal-v0", action_space=space)
    _, info = env.reset(seed=0)
    assert env.action_space.n == size == len(env.action_names) == len(info["valid_actions"])
    assert tuple(info["valid_actions"]) == ACTION_SPACES[space]
    assert env.action_names[:3] == ("turn left", "turn right", "go forward")


@pytest.mark.parametrize("env_id,size", [("BabyAI-GoToLocal-v0", 3), ("BabyAI-GoToRedBallGrey-v0", 3),
                                         ("BabyAI-UnlockLocal-v0", 6), ("BabyAI-PickupLoc-v0", 6),
                                         ("MiniGrid-DoorKey-5x5-v0", 6)])
def test_default_action_space_is_the_papers(env_id, size):
    """Paper Tables 1 and 5: the Go To levels have the 3 original actions; other levels keep 6."""
    env = make_env(env_id)
    _, info = env.reset(seed=0)
    assert len(env.action_names) == len(info["valid_actions"]) == env.action_space.n == size
    assert resolve_action_space(env_id) == {3: "original", 6: "augmented"}[size]


def test_explicit_action_space_wins():
    assert len(make_env("BabyAI-GoToLocal-v0", action_space="augmented").action_names) == 6
    assert len(make_env("BabyAI-UnlockLocal-v0", action_space="original").action_names) == 3
    assert resolve_action_space("BabyAI-GoToLocal-v0", "irrelevant") == "irrelevant"


def _bot_actions(env_id: str, seeds=range(3)) -> set[int]:
    """The MiniGrid actions the BabyAI expert bot takes to solve a few episodes of a level."""
    import contextlib
    import io

    import gymnasium as gym
    from minigrid.utils.baby_ai_bot import BabyAIBot

    env, used = gym.make(env_id), set()
    for seed in seeds:
        with contextlib.redirect_stdout(io.StringIO()):  # level generation chatter
            env.reset(seed=seed)
        bot = BabyAIBot(env.unwrapped)
        for _ in range(env.unwrapped.max_steps):
            action = int(bot.replan())
            used.add(action)
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
    return used


GOTO_IDS = [i for i in known_env_ids() if i.startswith("BabyAI-GoTo")]


@pytest.mark.parametrize("env_id", [i for i in GOTO_IDS if resolve_action_space(i) == "original"])
def test_goto_levels_given_the_original_actions_need_no_other(env_id):
    assert _bot_actions(env_id) <= {0, 1, 2}  # turn left, turn right, go forward


@pytest.mark.slow
@pytest.mark.parametrize("env_id", [i for i in GOTO_IDS if resolve_action_space(i) != "original"])
def test_goto_levels_behind_closed_doors_keep_the_augmented_actions(env_id):
    assert resolve_action_space(env_id) == "augmented" and _bot_actions(env_id) - {0, 1, 2}


def test_irrelevant_actions_only_consume_a_step():
    env = make_env("BabyAI-UnlockLocal-v0", action_space="irrelevant")
    env.reset(seed=1)
    for action in (1, 1, 2, 2, 2, 1, 3):  # the expert's way to the red key, then pick it up
        env.step(action)
    u = env.unwrapped
    assert u.carrying is not None and u.carrying.type == "key"
    for action in (6, 7, 8):
        before = (tuple(u.agent_pos), u.agent_dir, u.carrying, u.grid.encode().tobytes(), u.step_count)
        _, reward, terminated, truncated, info = env.step(action)
        after = (tuple(u.agent_pos), u.agent_dir, u.carrying, u.grid.encode().tobytes(), u.step_count)
        assert after[:4] == before[:4] and after[4] == before[4] + 1
        assert (reward, terminated, truncated) == (0, False, False)


def test_irrelevant_actions_run_into_the_time_limit():
    env = make_env("BabyAI-GoToLocal-v0", action_space="irrelevant")
    env.reset(seed=0)
    limit = env.unwrapped.max_steps
    assert limit > 0
    for t in range(1, limit + 1):
        _, _, terminated, truncated, _ = env.step(8)
        assert not terminated and truncated == (t == limit)


def test_bad_action_and_options():
    env = make_env("BabyAI-GoToLocal-v0", action_space="original")
    env.reset(seed=0)
    with pytest.raises(UsageError, match="0..2"):
        env.step(3)
    with pytest.raises(UsageError, match="irrelevant"):
        make_env("BabyAI-GoToLocal-v0", action_space="huge")
    with pytest.raises(UsageError, match="num_dists"):
        make_env("BabyAI-OpenDoor-v0", num_dists=4)


def test_irrelevant_space_refuses_babyai_done_actions(monkeypatch):
    from minigrid.envs.babyai.core import verifier

    monkeypatch.setattr(verifier, "use_done_actions", "1")
    with pytest.raises(UsageError, match="BABYAI_DONE_ACTIONS"):
        make_env("BabyAI-GoToLocal-v0", action_space="irrelevant")
    make_env("BabyAI-GoToLocal-v0", action_space="augmented")


def test_num_dists_reaches_the_level():
    assert make_env("BabyAI-GoToLocal-v0", num_dists=16).unwrapped.num_dists == 16


def test_registry():
    ids = known_env_ids()
    assert "BabyAI-GoToLocal-v0" in ids and "MiniGrid-DoorKey-8x8-v0" in ids
    assert all(i.startswith(("BabyAI-", "MiniGrid-", "MiniHack-", "Crafter", "ALE/")) for i in ids)
    assert renderer_of("BabyAI-GoToLocal-v0") == f"babyai-text@{RENDERER_VERSION}"


def test_unknown_env_id_suggests_close_matches():
    with pytest.raises(UnknownEnvError) as err:
        make_env("BabyAI-GoToLocl-v0")
    message = str(err.value)
    assert "BabyAI-GoToLocal-v0" in message and "\n" not in message
    suggestions = re.search(r"did you mean (.*?)\?", message).group(1).split(", ")
    assert 1 <= len(suggestions) <= 3 and suggestions[0] == "BabyAI-GoToLocal-v0"
    with pytest.raises(UnknownEnvError, match="illm envs"):
        renderer_of("NoSuchEnv-v0")
