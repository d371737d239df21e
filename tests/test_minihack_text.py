"""MiniHack-Text renderer (snapshots of the paper's five tasks, hand-built observations), missions,
action names and the task ids.

A snapshot mismatch means the rendered text changed: bump RENDERER_VERSION in
illm_tools/envs/minihack_text.py, check the new texts by eye, and paste them here.

Snapshots need a reproducible game: `gym.make(..., fix_moon_phase=True)` derives the moon phase
(and Friday the 13th) from the seed instead of today's date, and `_reset` seeds NetHack's RNGs
before the reset (NLE's reset(seed=...) seeds only gymnasium's RNG).
"""
from __future__ import annotations

import re
import warnings

import gymnasium as gym
import numpy as np
import pytest
from nle import nethack
from nle.env.base import NLE

from illm_tools.envs.minihack_actions import action_names
from illm_tools.envs.minihack_text import OBS_KEYS, RENDERER_VERSION, TASKS, describe, mission, render_text

RESET_TEXTS = {
    "River-Monster": ('message: Be careful! New moon tonight.; '
        'a jackal adjacent southeast (1 east, 1 south); '
        'a kobold zombie far east (6 east, 1 north); a boulder far east (8 east); '
        '2 boulders very far east (9 east, 1 south); '
        'water very far east (18 east, 3 south)'),
    "MultiRoom-N4-Monster": ('message: Be careful! New moon tonight.; a jackal adjacent north (1 north); '
        'a closed door adjacent south (1 south); a jackal adjacent west (1 west); '
        'walls adjacent northeast, east, southeast and southwest'),
    "LavaCross-Ring": ('message: Be careful! New moon tonight.; '
        'lava adjacent northeast (1 east, 1 north); lava adjacent east (1 east); '
        'lava adjacent southeast (1 east, 1 south); '
        'the staircase down very near northeast (2 east, 1 north); '
        'a ring near west (3 west, 1 north)'),
    "LavaCross-Potion": ('message: Be careful! New moon tonight.; '
        'lava adjacent northeast (1 east, 1 north); lava adjacent east (1 east); '
        'lava adjacent southeast (1 east, 1 south); '
        'the staircase down very near northeast (2 east, 1 north); '
        'a potion near west (3 west, 1 north)'),
    "LavaCross-Full": ('message: Be careful! New moon tonight.; '
        'lava very near northeast (2 east, 2 north); lava very near east (2 east); '
        'lava near northeast (2 east, 3 north); '
        'a pair of boots near northwest (3 west, 2 north); '
        'the staircase down far northeast (6 east, 4 north); '
        'walls adjacent southeast, south and southwest'),
}

_D, _C = nethack.CompassDirection, nethack.Command
_RING = "you carry a ring of levitation (on right hand)"
# LavaCross-Ring, seed 0: walk to the ring, pick it up, put it on (item f, right hand: the keys f
# and r are the actions FIRE and READ), float east over the lava next to the staircase down.
RING_STEPS = [
    (_D.W, 'the staircase up adjacent east (1 east); '
        'lava very near northeast (2 east, 2 north); lava very near east (2 east); '
        'lava very near southeast (2 east, 1 south); '
        'a ring very near northwest (2 west, 1 north); '
        'the staircase down near east (3 east, 1 north)'),
    (_D.W, 'a ring adjacent northwest (1 west, 1 north); '
        'the staircase up very near east (2 east); '
        'lava near northeast (3 east, 3 north); lava near east (3 east, 1 north); '
        'the staircase down near east (4 east, 1 north)'),
    (_D.NW, 'message: You see here an opal ring.; '
        'the staircase up near east (3 east, 1 south); '
        'lava near northeast (4 east, 2 north); lava near east (4 east, 1 north); '
        'lava near southeast (4 east, 2 south); the staircase down far east (5 east)'),
    (_C.PICKUP, 'message: f - an opal ring.; the staircase up near east (3 east, 1 south); '
        'lava near northeast (4 east, 2 north); lava near east (4 east, 1 north); '
        'lava near southeast (4 east, 2 south); the staircase down far east (5 east); '
        'you carry an opal ring'),
    (_C.PUTON, 'message: What do you want to put on? [f or ?*]; '
        'the staircase up near east (3 east, 1 south); '
        'lava near northeast (4 east, 2 north); lava near east (4 east, 1 north); '
        'lava near southeast (4 east, 2 south); the staircase down far east (5 east); '
        'you carry an opal ring'),
    (_C.FIRE, 'message: Which ring-finger, Right or Left? [rl]; '
        'the staircase up near east (3 east, 1 south); '
        'lava near northeast (4 east, 2 north); lava near east (4 east, 1 north); '
        'lava near southeast (4 east, 2 south); the staircase down far east (5 east); '
        'you carry an opal ring'),
    (_C.READ, 'message: f - a ring of levitation (on right hand).; you are levitating; '
        'the staircase up near east (3 east, 1 south); '
        'lava near northeast (4 east, 2 north); lava near east (4 east, 1 north); '
        'lava near southeast (4 east, 2 south); the staircase down far east (5 east); '
        'you carry a ring of levitation (on right hand)'),
    (_D.E, 'you are levitating; the staircase up very near southeast (2 east, 1 south); '
        'lava near northeast (3 east, 2 north); lava near east (3 east, 1 north); '
        'lava near southeast (3 east, 2 south); the staircase down near east (4 east); '
        'you carry a ring of levitation (on right hand)'),
    (_D.E, 'you are levitating; the staircase up adjacent southeast (1 east, 1 south); '
        'lava very near northeast (2 east, 2 north); lava very near east (2 east); '
        'lava very near southeast (2 east, 1 south); '
        'the staircase down near east (3 east); '
        'you carry a ring of levitation (on right hand)'),
    (_D.E, 'you are levitating; lava adjacent northeast (1 east, 1 north); '
        'lava adjacent east (1 east); lava adjacent southeast (1 east, 1 south); '
        'the staircase up adjacent south (1 south); '
        'the staircase down very near east (2 east); '
        'you carry a ring of levitation (on right hand)'),
    (_D.E, 'you are levitating; lava adjacent north (1 north); '
        'the staircase down adjacent east (1 east); lava adjacent south (1 south); '
        'the staircase up adjacent southwest (1 west, 1 south); '
        'lava very near north (2 north); you carry a ring of levitation (on right hand)'),
]


def _register_minihack() -> None:
    with warnings.catch_warnings():  # minihack imports pkg_resources, which warns
        warnings.simplefilter("ignore")
        import minihack  # noqa: F401  (registers the MiniHack-* ids)


def _make(env_id: str) -> gym.Env:
    _register_minihack()
    return gym.make(env_id, observation_keys=OBS_KEYS, fix_moon_phase=True)


def _reset(env: gym.Env, seed: int) -> dict:
    base = env.unwrapped
    if hasattr(base, "minigrid_env"):  # MultiRoom: MiniHack draws the layout with a MiniGrid env,
        base.minigrid_env.reset(seed=seed)  # and its seed() calls minigrid_env.seed(), gone from gymnasium
    NLE.seed(base, seed, seed, reseed=False)
    obs, _ = env.reset(seed=seed)
    return obs


def test_task_ids_are_registered():
    _register_minihack()
    assert set(TASKS) == {"River-Monster", "MultiRoom-N4-Monster", "LavaCross-Ring", "LavaCross-Potion",
                          "LavaCross-Full"}
    for env_id in TASKS.values():
        assert env_id in gym.registry, env_id


@pytest.mark.parametrize("task", sorted(TASKS))
def test_reset_snapshot(task):
    assert RENDERER_VERSION == 2, "snapshots of renderer version 2: regenerate them for the new version"
    env = _make(TASKS[task])
    try:
        assert render_text(_reset(env, 0)) == RESET_TEXTS[task], "text changed: bump RENDERER_VERSION"
    finally:
        env.close()


def test_lavacross_ring_steps_snapshot():
    env = _make(TASKS["LavaCross-Ring"])
    try:
        _reset(env, 0)
        actions = env.unwrapped.actions
        for action, expected in RING_STEPS:
            obs, _, terminated, truncated, _ = env.step(actions.index(action))
            assert not (terminated or truncated)
            assert render_text(obs) == expected, f"after {action!r}: text changed: bump RENDERER_VERSION"
    finally:
        env.close()


# ------------------------------------------------------------------------------ hand-built observations

AGENT_X, AGENT_Y = 40, 10
FLOOR = nethack.GLYPH_CMAP_OFF + 19  # "floor of a room"
WALL = nethack.GLYPH_CMAP_OFF + 1
STAIRS_DOWN = nethack.GLYPH_CMAP_OFF + 24
LAVA = nethack.GLYPH_CMAP_OFF + 34


def _monster(name: str) -> int:
    return next(nethack.GLYPH_MON_OFF + i for i in range(nethack.NUMMONS)
                if nethack.permonst(i).mname == name)


def _object(name: str, cls: int) -> int:
    return next(nethack.GLYPH_OBJ_OFF + i for i in range(nethack.NUM_OBJECTS)
                if nethack.OBJ_NAME(nethack.objclass(i)) == name and ord(nethack.objclass(i).oc_class) == cls)


def _obs(*cells: tuple[int, int, int], message: str = "", inventory: tuple[str, ...] = (), hp: int = 14,
         condition: int = 0) -> dict:
    """A room floor with the agent at (AGENT_X, AGENT_Y) and (dx, dy, glyph) cells around it."""
    glyphs = np.full((nethack.DUNGEON_SHAPE), FLOOR, dtype=np.int16)
    glyphs[AGENT_Y, AGENT_X] = _monster("human")
    for dx, dy, glyph in cells:
        assert 0 <= AGENT_Y + dy < glyphs.shape[0] and 0 <= AGENT_X + dx < glyphs.shape[1]
        glyphs[AGENT_Y + dy, AGENT_X + dx] = glyph
    blstats = np.zeros(nethack.NLE_BLSTATS_SIZE, dtype=np.int64)
    blstats[nethack.NLE_BL_X], blstats[nethack.NLE_BL_Y] = AGENT_X, AGENT_Y
    blstats[nethack.NLE_BL_HP], blstats[nethack.NLE_BL_HPMAX] = hp, 14
    blstats[nethack.NLE_BL_CONDITION] = condition
    msg = np.zeros(nethack.NLE_MESSAGE_SIZE, dtype=np.uint8)
    msg[:len(message)] = np.frombuffer(message.encode(), dtype=np.uint8)
    inv_strs = np.zeros((nethack.NLE_INVENTORY_SIZE, nethack.NLE_INVENTORY_STR_LENGTH), dtype=np.uint8)
    for row, item in enumerate(inventory):
        inv_strs[row, :len(item)] = np.frombuffer(item.encode(), dtype=np.uint8)
    return {"glyphs": glyphs, "message": msg, "blstats": blstats, "inv_strs": inv_strs}


_OFFSET = re.compile(r" \((?:\d+ (?:east|west|north|south)(?:, )?)+\)$")


def _words(phrases: list[str]) -> list[str]:
    """The phrases without their offsets (version 2's "(3 east, 1 north)"), for the tests of the words."""
    return [_OFFSET.sub("", p) for p in phrases]


@pytest.mark.parametrize("dx,dy,expected", [
    (1, 0, "a newt adjacent east"), (-1, -1, "a newt adjacent northwest"), (0, 1, "a newt adjacent south"),
    (0, -2, "a newt very near north"), (2, -1, "a newt very near northeast"),
    (-2, 2, "a newt very near southwest"), (3, -1, "a newt near east"), (3, 3, "a newt near southeast"),
    (-4, 1, "a newt near west"), (-5, 2, "a newt far west"), (1, -8, "a newt far north"),
    (6, 5, "a newt far southeast"), (9, 0, "a newt very far east"), (-12, -9, "a newt very far northwest"),
    (-30, 7, "a newt very far west"),
])
def test_direction_and_distance_words(dx, dy, expected):
    assert _words(describe(_obs((dx, dy, _monster("newt"))))) == [expected]


def test_agent_square_and_floor_are_not_described_and_walls_only_where_adjacent():
    obs = _obs((1, 0, WALL), (-1, 0, WALL), (0, 1, nethack.GLYPH_CMAP_OFF))  # walls, dark part of a room
    assert describe(obs) == ["walls adjacent east and west"]
    assert describe(_obs((0, -1, WALL), (2, 0, WALL))) == ["a wall adjacent north"]
    assert describe(_obs((3, 0, WALL))) == []


@pytest.mark.parametrize("dx,dy,offset", [(1, 0, "1 east"), (-2, -1, "2 west, 1 north"), (0, 5, "5 south"),
                                          (-7, 3, "7 west, 3 south")])
def test_a_phrase_gives_the_offset_of_its_nearest_square(dx, dy, offset):
    (phrase,) = describe(_obs((dx, dy, _monster("newt"))))
    assert phrase.endswith(f" ({offset})")
    boulder = _object("boulder", nethack.ROCK_CLASS)  # two squares in one phrase: the nearer one's offset
    assert describe(_obs((4, 0, boulder), (3, 0, boulder))) == ["2 boulders near east (3 east)"]


def test_things_are_named_grouped_and_ordered_nearest_first():
    boulder = _object("boulder", nethack.ROCK_CLASS)
    obs = _obs((3, 0, boulder), (4, 0, boulder), (0, 3, LAVA), (0, 4, LAVA), (5, -5, STAIRS_DOWN),
               (-1, 0, nethack.GLYPH_PET_OFF + nethack.glyph_to_mon(_monster("little dog"))),
               (-2, 0, _object("levitation", nethack.POTION_CLASS)),
               (0, -2, _object("levitation boots", nethack.ARMOR_CLASS)),
               (2, 2, nethack.GLYPH_CMAP_OFF + 12), (-3, -3, nethack.GLYPH_CMAP_OFF + 15))
    assert _words(describe(obs)) == [
        "a tame little dog adjacent west", "a pair of boots very near north", "a doorway very near southeast",
        "a potion very near west", "2 boulders near east", "lava near south", "a closed door near northwest",
        "the staircase down far northeast"]


def test_at_most_three_phrases_per_thing_and_twelve_in_all_keeping_the_staircase_down():
    newt, jackal = _monster("newt"), _monster("jackal")
    cells = [(dx, 1, newt) for dx in (-6, -3, 0, 3, 6)]  # 5 groups: the 3 nearest are kept
    cells += [(dx, -6, jackal) for dx in (-7, -3, 0, 3, 7)]  # 3 groups: far northwest, north, northeast
    cells += [(0, 2, LAVA), (1, 3, LAVA), (-9, -9, LAVA), (2, 9, nethack.GLYPH_CMAP_OFF + 12),
              (-10, 0, nethack.GLYPH_CMAP_OFF + 15), (-12, 0, nethack.GLYPH_CMAP_OFF + 31)]  # 6 features
    cells += [(15, -9, STAIRS_DOWN)]
    # 13 phrases: the staircase down, then monsters and objects, then the nearest features are kept,
    # so the farthest feature (the fountain) goes.
    assert _words(describe(_obs(*cells))) == [
        "a newt adjacent south", "lava very near south", "a newt near east", "lava near south",
        "a newt near west", "a jackal far north", "2 jackals far northeast", "2 jackals far northwest",
        "a doorway very far south",
        "lava very far northwest", "a closed door very far west", "the staircase down very far northeast"]


def test_message_status_and_inventory():
    obs = _obs((1, 0, _monster("newt")), message="You see here an opal ring.   ", hp=2,
               condition=nethack.BL_MASK_LEV | nethack.BL_MASK_CONF,
               inventory=("a +1 club (weapon in hand)", "17 uncursed flint stones (in quiver pouch)",
                          "30 uncursed rocks", "an uncursed very burnt +0 leather armor (being worn)",
                          "an uncursed blindfold",
                          "an uncursed potion of sickness", "an empty uncursed sack", "an opal ring",
                          "a ring of levitation (on right hand)", "2 uncursed daggers named sting"))
    assert describe(obs) == [
        "message: You see here an opal ring.", "you are levitating and confused",
        "your hit points are low (2 of 14)",
        "a newt adjacent east (1 east)",
        "you carry an opal ring, a ring of levitation (on right hand), 2 uncursed daggers named sting"]
    assert render_text(obs) == "; ".join(describe(obs))


def test_hit_points_are_low_at_most_5_or_a_seventh():
    assert describe(_obs(hp=6)) == []
    assert describe(_obs(hp=5)) == ["your hit points are low (5 of 14)"]


def test_articles_and_plurals():
    statue = nethack.GLYPH_STATUE_OFF + nethack.glyph_to_mon(_monster("Medusa"))
    gold = _object("gold piece", nethack.COIN_CLASS)
    stairs_up = nethack.GLYPH_CMAP_OFF + 23
    obs = _obs((1, 0, _monster("Medusa")), (0, 1, _monster("Oracle")), (-1, 0, _monster("owlbear")),
               (0, -1, statue), (3, 0, gold), (4, 0, gold), (3, 3, _monster("dwarf")),
               (4, 4, _monster("dwarf")), (-3, 0, stairs_up), (-4, 0, stairs_up))
    assert _words(describe(obs)) == ["a statue of Medusa adjacent north", "Medusa adjacent east", "the Oracle adjacent south",
                             "an owlbear adjacent west", "gold near east", "2 dwarves near southeast",
                             "2 staircases up near west"]


# --------------------------------------------------------------------------------- actions, missions

@pytest.mark.parametrize("task", sorted(TASKS))
def test_action_names_are_unique_and_readable(task):
    env = _make(TASKS[task])
    try:
        names = action_names(env.unwrapped.actions)
    finally:
        env.close()
    assert len(names) == len(env.unwrapped.actions) and len(set(names)) == len(names)
    assert all(re.fullmatch(r"[a-z0-9 ()-]+", name) for name in names), names
    assert names[:8] == ("move north", "move east", "move south", "move west", "move northeast",
                         "move southeast", "move southwest", "move northwest")
    if task.startswith("LavaCross"):
        expected = {"pick up", "put on", "drink (quaff)", "apply", "zap", "wear", "run north", "type plus sign"}
        assert expected <= set(names)


def test_every_nle_action_has_a_distinct_name():
    names = action_names(nethack.ACTIONS)
    assert len(set(names)) == len(nethack.ACTIONS)
    assert action_names([_C.SEESPELLS, nethack.TextCharacters.PLUS, nethack.TextCharacters.NUM_7, _C.QUAFF]) == (
        "show spells", "type plus sign", "type 7", "drink (quaff)")


def test_missions():
    assert mission(TASKS["River-Monster"]) == ("cross the river by pushing boulders into it, "
                                              "and reach the staircase down")
    assert mission(TASKS["LavaCross-Ring"]).startswith("pick up the ring of levitation, put it on")
    assert mission(TASKS["LavaCross-Potion"]).startswith("pick up the potion of levitation, drink it")
    assert "wand of cold" in mission(TASKS["LavaCross-Full"])
    assert mission(TASKS["MultiRoom-N4-Monster"]) == ("go through the rooms and their doors "
                                                     "to reach the staircase down")
    assert mission("MiniHack-Room-5x5-v0") == "reach the staircase down"
    assert mission("MiniHack-LavaCross-Levitate-Ring-Inv-Full-v0").startswith("put on the ring of levitation")
