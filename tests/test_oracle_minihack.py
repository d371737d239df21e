"""The MiniHack oracle (illm_tools.oracles.minihack): its reading of MiniHack-Text, its game
knowledge checked against NLE, and hand-checked rankings on states of the paper's tasks."""

from __future__ import annotations

import random

import pytest
from nle import nethack

from illm_tools.envs import make_env
from illm_tools.envs.minihack_actions import action_names
from illm_tools.envs.minihack_text import _DIRECTIONS
from illm_tools.oracles.base import Scene
from illm_tools.oracles.minihack import DEADLY, MiniHackOracle
from illm_tools.oracles.minihack_reading import DIRECTIONS, KEYS, read_view

MOVES = tuple(f"move {d}" for d in ("north", "east", "south", "west", "northeast", "southeast", "southwest",
                                    "northwest"))
LAVA_ACTIONS = (*MOVES, "pick up", "put on", "fire", "read")
RING = "pick up the ring of levitation, put it on, float over the lava and reach the staircase down"
STAIRS = "reach the staircase down"


def _best(text: str, mission: str = STAIRS, actions=MOVES, history=()) -> list[str]:
    costs = MiniHackOracle().costs(Scene("MiniHack", mission, tuple(history), text, tuple(actions)))
    low = min(costs.values())
    return sorted(a for a, c in costs.items() if c == low)


def _costs(text: str, mission: str = STAIRS, actions=MOVES) -> dict[str, float]:
    return MiniHackOracle().costs(Scene("MiniHack", mission, (), text, tuple(actions)))


def test_its_keys_and_directions_are_the_renderer_s_and_nle_s():
    assert tuple(DIRECTIONS) == _DIRECTIONS
    named = dict(zip((int(a) for a in nethack.ACTIONS), action_names(nethack.ACTIONS)))
    for key, name in KEYS.items():
        assert named.get(ord(key)) == name, (key, name, named.get(ord(key)))


def test_it_reads_a_rendered_observation_of_lavacross():
    env = make_env("MiniHack-LavaCross-Levitate-Ring-Pickup-Restricted-v0")
    try:
        _, info = env.reset(seed=1)
    finally:
        env.close()
    view = read_view(info["text"])
    ring = view.of("ring")[0]
    stairs = view.of("staircase down")[0]
    assert (ring.dx, ring.dy) == (-3, -3) and (stairs.dx, stairs.dy) == (5, 1) and not view.levitating
    assert _best(info["text"], RING, LAVA_ACTIONS) == ["move northwest"]  # to the ring, away from the lava


def test_lava_is_deadly_without_levitation_and_a_floor_while_levitating():
    text = "lava adjacent east (1 east); the staircase down near east (4 east)"
    costs = _costs(text)
    assert costs["move east"] >= min(costs.values()) + DEADLY
    assert _best(f"you are levitating; {text}") == ["move east", "move northeast", "move southeast"]  # diagonals count one move


def test_the_levitation_plan_picks_up_puts_on_answers_the_prompts_and_crosses():
    here = "message: You see here an opal ring.; lava near east (4 east); the staircase down far east (5 east)"
    assert _best(here, RING, LAVA_ACTIONS) == ["pick up"]
    carried = "lava near east (4 east); the staircase down far east (5 east); you carry an opal ring"
    assert _best(carried, RING, LAVA_ACTIONS) == ["put on"]
    asked = f"message: What do you want to put on? [f or ?*]; {carried}"
    assert _best(asked, RING, LAVA_ACTIONS) == ["fire"]  # f: the ring's letter, the key of "fire"
    finger = f"message: Which ring-finger, Right or Left? [rl]; {carried}"
    assert _best(finger, RING, LAVA_ACTIONS) == ["read"]  # r
    worn = ("you are levitating; lava adjacent east (1 east); the staircase down near east (3 east); "
            "you carry a ring of levitation (on right hand)")
    assert _best(worn, RING, LAVA_ACTIONS) == ["move east", "move northeast", "move southeast"]
    potion = "lava near east (4 east); you carry a bubbly potion"
    mission = "pick up the potion of levitation, drink it, float over the lava and reach the staircase down"
    assert _best(potion, mission, (*MOVES, "pick up", "drink (quaff)", "fire")) == ["drink (quaff)"]


def test_monsters_are_fought_where_they_stand_unless_the_stairs_are_a_step_away():
    jackal = "a jackal adjacent west (1 west); the staircase down far east (6 east)"
    assert _best(jackal) == ["move west"]
    assert _best("a jackal adjacent west (1 west); the staircase down adjacent east (1 east)") == ["move east"]


def test_walls_and_doorways_are_gone_around_and_doors_entered_straight():
    assert "move north" not in _best("walls adjacent north and northeast; the staircase down far north (1 east, 6 north)")
    # a door one step away diagonally is entered straight: step beside it first
    door = "a closed door adjacent southeast (1 east, 1 south); walls adjacent south and southwest"
    assert "move southeast" not in _best(door) and _best(door) == ["move east"]
    stuck = "message: You can't move diagonally out of an intact doorway.; the staircase down near northeast (3 east, 3 north)"
    assert set(_best(stuck)) <= {"move north", "move east"}


def test_closed_doors_lead_on_and_with_nothing_in_view_any_free_step_will_do():
    doors = "an open door very near west (2 west); a closed door near east (4 east)"
    assert _best(doors) == ["move east", "move northeast", "move southeast"]
    assert set(_best("walls adjacent north and west")) == set(MOVES) - {"move north", "move west"}


def test_texts_and_the_noised_grammar():
    oracle = MiniHackOracle()
    scene = Scene("MiniHack", RING, (), "a ring near northwest (2 west, 3 north); lava near east (4 east)", LAVA_ACTIONS)
    assert oracle.text(scene, "goal").startswith("pick up the ring")
    assert oracle.text(scene, "plan") == "move northwest, move northwest, move north"
    assert oracle.text(scene, "summary") == ("The agent must pick up the ring. The ring is 3 steps away. "
                                             "It carries nothing.")
    rng = random.Random(0)
    assert oracle.random_text(scene, "summary", rng).startswith("The agent must reach the")


@pytest.mark.parametrize("env_id", ["MiniHack-Room-5x5-v0", "MiniHack-LavaCross-Levitate-Potion-Pickup-Restricted-v0"])
def test_the_oracle_solves_small_levels_acting_on_its_ranking(env_id):
    from illm_tools.acting import ActConfig, act
    from illm_tools.llm.spec import LLMSpec

    figures = act(ActConfig(env_id=env_id, llm=LLMSpec("oracle", "oracle"), episodes=3))
    mine, random_policy = figures["policies"]["annotator"], figures["policies"]["random"]
    assert mine["episodes"] == random_policy["episodes"] == 3
    assert mine["success_rate"] == 1.0 and mine["mean_length"] < random_policy["mean_length"]
