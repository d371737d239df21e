"""Crafter-Text renderer (snapshots on fixed seeds, a hand-built scene, the semantic map), action and
achievement names, and the Crafter score.

The snapshot strings were checked against crafter's own image of each state. A mismatch means the
rendered text changed: bump RENDERER_VERSION in illm_tools/envs/crafter_text.py and paste the new texts.

Crafter 1.8.3 is not reproducible across processes for a fixed seed and action sequence: every 10th
step `Env._balance_object` despawns `creatures[random.randint(...)]`, a list built from a chunk's
*set* of objects, whose order follows the objects' memory addresses. The `_deterministic_balance`
fixture hands it each chunk's objects sorted by position instead, so the snapshots hold in every run.
"""
from __future__ import annotations

import math

import crafter
import numpy as np
import pytest
from crafter import engine, objects

from illm_tools.envs.crafter_text import (ACHIEVEMENTS, ACTION_NAMES, MISSION, RENDERER_NAME, RENDERER_VERSION,
                                          achievement_success_rates, crafter_score, describe, render_text)
from illm_tools.errors import UsageError

ACTION = {name: index for index, name in enumerate(crafter.constants.actions)}

# Seed 0: down to the trees south-east of the start, collect 3 wood, place a table, make a pickaxe, walk on.
WOOD_PICKAXE_RUN = (["move_down"] * 3 + ["move_right"] * 3 + ["do", "move_down", "do"] + ["move_right"] * 3
                    + ["move_up", "do", "place_table", "make_wood_pickaxe", "move_right", "move_right", "move_up",
                       "move_up"])
# Seed 0: straight north to the edge of a mountain (stone, coal) past sand.
NORTH_RUN = ["move_up"] * 25

SNAPSHOTS = [
    ([], "You face grass; You see a cow 4 steps east, a tree 7 steps north-west; You have nothing; "
         "Health 9/9, food 9/9, drink 9/9, energy 9/9"),
    (WOOD_PICKAXE_RUN[:6], "You face a tree; You see a tree 1 step east, a cow 6 steps north-east; You have nothing; "
                           "Health 9/9, food 9/9, drink 9/9, energy 9/9"),
    (WOOD_PICKAXE_RUN[:14], "You face grass; You see a tree 1 step south, a cow 4 steps north; You have 3 wood; "
                            "Health 9/9, food 9/9, drink 9/9, energy 9/9"),
    (WOOD_PICKAXE_RUN, "You face a tree; You see a tree 1 step north, a table 2 steps west, a cow 4 steps west; "
                       "You have 1 wood pickaxe; Health 9/9, food 9/9, drink 9/9, energy 9/9"),
    (NORTH_RUN, "You face a tree; You see a tree 1 step north, stone 3 steps east, coal 4 steps east; "
                "You have nothing; Health 9/9, food 9/9, drink 8/9, energy 9/9"),
]


@pytest.fixture(autouse=True)
def _deterministic_balance(monkeypatch):
    monkeypatch.setattr(engine.World, "chunks", property(
        lambda world: {chunk: sorted(objs, key=lambda obj: tuple(obj.pos)) for chunk, objs in world._chunks.items()}))


def _run(actions: list[str], seed: int = 0) -> tuple[crafter.Env, dict]:
    env = crafter.Env(seed=seed)
    env.reset()
    info: dict = {}
    for name in actions:
        _, _, done, info = env.step(ACTION[name])
        assert not done
    return env, info


def test_names_follow_crafter():
    assert RENDERER_NAME == "crafter-text" and isinstance(RENDERER_VERSION, int)
    assert len(ACTION_NAMES) == len(set(ACTION_NAMES)) == len(crafter.constants.actions) == 17
    assert ACTION_NAMES[:7] == ("do nothing", "move west", "move east", "move north", "move south", "interact",
                                "sleep")
    # the rest are crafter's names in words, in crafter's order
    assert ACTION_NAMES[7:] == tuple(name.replace("_", " ") for name in crafter.constants.actions[7:])
    assert ACHIEVEMENTS == tuple(crafter.constants.achievements) and len(ACHIEVEMENTS) == 22
    assert MISSION and "\n" not in MISSION


@pytest.mark.parametrize(("actions", "expected"), SNAPSHOTS, ids=["reset", "facing-tree", "3-wood", "pickaxe", "north"])
def test_snapshots(actions, expected):
    env, _ = _run(actions)
    assert render_text(env) == expected
    assert render_text(env) == "; ".join(describe(env))


def _blank_view(env: crafter.Env) -> None:
    """Grass over the whole 9x7 view and no objects in it but the player."""
    world, (px, py) = env._world, env._player.pos
    for dx in range(-4, 5):
        for dy in range(-3, 4):
            world[px + dx, py + dy] = "grass"
    for obj in world.objects:
        if obj is not env._player and abs(obj.pos[0] - px) <= 4 and abs(obj.pos[1] - py) <= 3:
            world.remove(obj)


def test_hand_built_scene_directions_distances_and_ties():
    env = crafter.Env(seed=0)
    env.reset()
    _blank_view(env)
    world, player = env._world, env._player
    px, py = player.pos
    assert tuple(player.facing) == (0, 1)  # crafter starts the player facing south (down)
    materials = {(-2, 0): "water", (0, -3): "water", (0, 1): "tree", (-1, 0): "tree", (3, 1): "stone", (2, 1): "coal",
                 (-1, 3): "iron", (4, 3): "diamond", (-4, -1): "lava", (0, 2): "table", (1, 3): "furnace",
                 (3, -1): "sand", (-3, 1): "path"}
    for (dx, dy), material in materials.items():
        world[px + dx, py + dy] = material
    ripe = objects.Plant(world, (px + 2, py - 2))
    ripe.grown = 301
    for obj in (objects.Zombie(world, (px + 1, py - 1), player), objects.Cow(world, (px - 3, py - 3)),
                objects.Skeleton(world, (px + 4, py - 3), player), ripe, objects.Plant(world, (px - 2, py + 2)),
                objects.Arrow(world, (px - 1, py - 2), (1, 0))):
        world.add(obj)
    rest = ("a zombie 2 steps north-east, water 2 steps west, a table 2 steps south, an arrow 3 steps north-west, "
            "coal 3 steps south-east, a ripe plant 4 steps north-east, a plant 4 steps south-west, stone 4 steps east, "
            "iron 4 steps south, a furnace 4 steps south, lava 5 steps west, a cow 6 steps north-west, "
            "a skeleton 7 steps north-east, a diamond 7 steps south-east")
    # the faced tree (south) wins the tie with the tree west; equal distances go by kind order
    assert describe(env) == ["You face a tree", f"You see a tree 1 step south, {rest}", "You have nothing",
                             "Health 9/9, food 9/9, drink 9/9, energy 9/9"]
    player.facing = (-1, 0)
    assert describe(env)[:2] == ["You face a tree", f"You see a tree 1 step west, {rest}"]
    player.facing = (1, 0)
    assert describe(env)[:2] == ["You face grass", f"You see a tree 1 step west, {rest}"]
    player.facing = (0, -1)
    assert describe(env)[0] == "You face grass"
    world.remove(world[px + 1, py - 1][1])  # the zombie
    player.facing = (1, 0)
    world.add(objects.Zombie(world, (px + 1, py), player))
    assert describe(env)[0] == "You face a zombie"


def test_empty_view_inventory_vitals_sleep_and_world_edge():
    env = crafter.Env(seed=0)
    env.reset()
    _blank_view(env)
    player = env._player
    player.inventory.update(wood=2, sapling=3, wood_pickaxe=1, stone_sword=2, health=5, drink=0)
    player.sleeping = True
    assert describe(env) == ["You are sleeping", "You face grass",
                             "You have 3 saplings, 2 wood, 1 wood pickaxe, 2 stone swords",
                             "Health 5/9, food 9/9, drink 0/9, energy 9/9"]
    env._world.move(player, (0, 32))  # the west edge of the 64x64 world; the view reaches past it
    player.facing = (-1, 0)
    assert describe(env)[1] == "You face the edge of the world"


def test_the_edge_of_the_world_is_seen():
    """Renderer version 2: the nearest cell past the map's border is named like any thing of interest
    (always straight along an axis; at a corner, the tie goes north first like every tie)."""
    assert RENDERER_VERSION == 2
    env = crafter.Env(seed=0)
    env.reset()
    player = env._player
    env._world.move(player, (0, 32))
    player.facing = (-1, 0)
    assert describe(env)[:2] == ["You face the edge of the world",
                                 "You see the edge of the world 1 step west, a tree 2 steps north-east, a cow 4 steps east, "
                                 "stone 6 steps south-east"]
    env._world.move(player, (62, 1))  # 2 steps from the north border and 2 from the east one
    player.facing = (0, -1)
    assert "the edge of the world 2 steps north" in describe(env)[1]
    env._world.move(player, (32, 32))  # the middle: no border in view
    assert "edge" not in render_text(env)


def test_directions_agree_with_the_semantic_map():
    env, info = _run(NORTH_RUN)
    semantic, (px, py) = info["semantic"], info["player_pos"]
    ids = env._world._mat_ids
    assert semantic[px, py] == env._sem_view._obj_ids[objects.Player]  # indexed [x, y] like the world
    view = semantic[px - 4: px + 5, py - 3: py + 4]  # the 9x7 cells the image shows
    text = render_text(env)
    for material, phrase in (("tree", "a tree"), ("stone", "stone"), ("coal", "coal")):
        xs, ys = np.nonzero(view == ids[material])
        dists = np.abs(xs - 4) + np.abs(ys - 3)
        nearest = int(dists.min())
        assert f"{phrase} {nearest} step" in text, (material, text)
    # coal lies east of the agent (larger x) and a tree right above it (smaller y: north)
    xs, ys = np.nonzero(view == ids["coal"])
    assert (xs > 4).all()
    assert view[4, 2] == ids["tree"] and "You face a tree" in text and "a tree 1 step north" in text


def _percent(rates: dict[str, float]) -> dict[str, float]:
    return {name: 100 * rate for name, rate in rates.items()}


def test_crafter_score():
    zero = dict.fromkeys(ACHIEVEMENTS, 0.0)
    assert crafter_score(zero) == 0.0
    assert crafter_score(dict.fromkeys(ACHIEVEMENTS, 100.0)) == pytest.approx(100.0)  # exp(ln 101) - 1
    assert crafter_score(dict.fromkeys(ACHIEVEMENTS, 50.0)) == pytest.approx(50.0)
    # collect_wood 100 %, collect_drink 50 %, the other 20 at 0 %: exp((ln 101 + ln 51) / 22) - 1
    mixed = {**zero, "collect_wood": 100.0, "collect_drink": 50.0}
    assert crafter_score(mixed) == pytest.approx(0.474763, abs=1e-6)
    assert crafter_score(mixed) == pytest.approx(math.exp((math.log(101) + math.log(51)) / 22) - 1)
    with pytest.raises(UsageError, match="missing: collect_coal"):
        crafter_score({name: 0.0 for name in ACHIEVEMENTS[1:]})
    with pytest.raises(UsageError, match="unknown: achievement_collect_coal"):
        crafter_score({**zero, "achievement_collect_coal": 0.0})
    with pytest.raises(UsageError, match="percentages in 0..100"):
        crafter_score({**zero, "collect_wood": 101.0})


def test_achievement_success_rates():
    episodes = [{"collect_wood": 3, "place_table": 1}, {"collect_wood": 1, "wake_up": 0}, {}, {"eat_cow": 2}]
    rates = achievement_success_rates(episodes)
    assert list(rates) == list(ACHIEVEMENTS)
    assert rates["collect_wood"] == 0.5 and rates["place_table"] == 0.25 and rates["eat_cow"] == 0.25
    assert rates["wake_up"] == 0.0 and sum(rates.values()) == 1.0
    assert crafter_score(_percent(rates)) == pytest.approx(math.exp((math.log(51) + 2 * math.log(26)) / 22) - 1)
    with pytest.raises(UsageError, match="no episodes"):
        achievement_success_rates([])
    with pytest.raises(UsageError, match="unknown Crafter achievement"):
        achievement_success_rates([{"achievement_collect_wood": 1}])


def test_real_episode_achievements_feed_the_score():
    _, info = _run(WOOD_PICKAXE_RUN)
    rates = achievement_success_rates([info["achievements"], dict.fromkeys(ACHIEVEMENTS, 0)])
    assert {name for name, rate in rates.items() if rate} == {"collect_wood", "place_table", "make_wood_pickaxe"}
    assert crafter_score(_percent(rates)) == pytest.approx(math.exp(3 * math.log(51) / 22) - 1)
