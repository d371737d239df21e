"""The Crafter oracle (`illm_tools.oracles.crafter`): its names and rules against crafter_text's and
crafter's own, hand-checked rankings on real states of `CrafterReward-v1` (recorded along a seeded
run, or built by placing things in a real world and rendered as `illm annotate` renders them, history
0), what the chosen action does when the env takes it, its texts, its refusals, its answers through
the oracle backend (rankings that follow the state; noise 1: random answers of its grammar), and a
seeded episode played on its own ranking."""

from __future__ import annotations

import random

import crafter
import pytest
from crafter import objects

from illm_tools.envs import make_env, suite_of
from illm_tools.envs import crafter_text
from illm_tools.errors import UsageError
from illm_tools.llm.oracle import OracleBackend
from illm_tools.oracles import crafter_planner, crafter_reading
from illm_tools.oracles.base import Scene, parse_prompt
from illm_tools.oracles.crafter import CrafterOracle
from illm_tools.oracles.crafter_paths import PICKAXE, UNREACHABLE
from illm_tools.oracles.registry import oracle_for
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.state import StateRecord

ENV = "CrafterReward-v1"
ACTION = {name: i for i, name in enumerate(crafter_text.ACTION_NAMES)}
BUILDER = PromptBuilder(env_id=ENV, renderer=suite_of(ENV).renderer, model_fingerprint="f", model="oracle",
                        history_len=0)
ORACLE = CrafterOracle()


def prompt(text: str, history=()) -> str:
    return BUILDER.render("action", StateRecord(crafter_text.MISSION, tuple(history), text,
                                                crafter_text.ACTION_NAMES)).text


def answer(text: str, history=()):
    return ORACLE.planner.answer(parse_prompt(prompt(text, history)))


def best(text: str, history=()) -> str:
    costs = answer(text, history).costs
    return min(costs, key=costs.get)


def world(seed: int = 0, *, facing=(0, 1), items=None, things=None):
    """A real env after reset, its view turned to grass and emptied (`things` then placed: offset ->
    a material or an object class), the player's facing and inventory set; returns (env, text)."""
    env = make_env(ENV)
    env.reset(seed=seed)
    game = env.unwrapped._env
    w, player = game._world, game._player
    px, py = (int(v) for v in player.pos)
    for obj in w.objects:
        if obj is not player and abs(obj.pos[0] - px) <= 5 and abs(obj.pos[1] - py) <= 4:
            w.remove(obj)
    for dx in range(-5, 6):
        for dy in range(-4, 5):
            w[px + dx, py + dy] = "grass"
    for (dx, dy), thing in (things or {}).items():
        if isinstance(thing, str):
            w[px + dx, py + dy] = thing
        else:
            w.add(thing(w, (px + dx, py + dy), player) if thing in (objects.Zombie, objects.Skeleton)
                  else thing(w, (px + dx, py + dy)))
    player.facing = facing
    player.inventory.update({k.replace(" ", "_"): v for k, v in (items or {}).items()})
    return env, crafter_text.render_text(game)


def take(env, action: str) -> str:
    _, _, _, _, info = env.step(ACTION[action])
    return info["text"]


# --- names and rules -------------------------------------------------------------------------------
def test_names_and_rules_agree_with_crafter_text_and_crafter():
    r = crafter_reading
    assert r.RENDERER == f"{crafter_text.RENDERER_NAME}@{crafter_text.RENDERER_VERSION}" == suite_of(ENV).renderer
    assert r.SIGHT_ORDER == crafter_text._SIGHT_ORDER
    assert set(r.FACE_PHRASES) == {*crafter_text._MATERIALS.values(), *crafter_text._OBJECTS.values(), "a ripe plant"}
    assert r.ACTIONS == crafter_text.ACTION_NAMES
    assert r.ITEMS == tuple(n.replace("_", " ") for n in crafter.constants.items if n not in r.VITALS)
    assert r.COUNTABLE == tuple(n.replace("_", " ") for n in crafter_text._COUNTABLE_ITEMS)
    assert r.VITALS == crafter_text._VITALS and set(r.GROUND) == set(crafter.constants.walkable)
    env = make_env(ENV)
    assert tuple(2 * h + 1 for h in r.HALF_VIEW) == tuple(int(n) for n in env.unwrapped._env._local_view._grid)
    words = lambda d: {k.replace("_", " "): v for k, v in d.items()}  # noqa: E731
    place = {k: (words(v["uses"]), tuple(v["where"])) for k, v in crafter.constants.place.items()}
    assert place == crafter_planner.PLACE
    assert {k.replace("_", " "): (words(v["uses"]), tuple(v["nearby"])) for k, v in crafter.constants.make.items()} \
        == crafter_planner.MAKE
    needs = {k: next(iter(words(v["require"])), None) for k, v in crafter.constants.collect.items()}
    assert {k: needs[k] for k in PICKAXE} == PICKAXE
    for dist in range(1, 8):  # every offset in view is a candidate of exactly the compass point the renderer writes
        for dx in range(-4, 5):
            for dy in range(-3, 4):
                if abs(dx) + abs(dy) == dist:
                    assert (dx, dy) in r.candidates(dist, crafter_text._direction(dx, dy))
    assert oracle_for("Crafter") == "crafter" and CrafterOracle.families == ("Crafter",)
    OracleBackend.check_use(ENV, suite_of(ENV).renderer)


# --- hand-checked rankings on real states ---------------------------------------------------------
def test_a_tree_faced_with_no_wood_is_struck_on_a_recorded_state():
    env = make_env(ENV)
    _, info = env.reset(seed=0)
    for name in ("move south",) * 3 + ("move east",) * 3:  # tests/test_crafter_text.py's seed-0 run to the trees
        _, _, _, _, info = env.step(ACTION[name])
    text = info["text"]
    assert text.startswith("You face a tree; You see a tree 1 step east") and "You have nothing" in text
    assert best(text) == "interact" and answer(text).step.text == "collect wood"
    assert "You have 1 wood" in take(env, "interact")


def test_a_tree_in_view_is_walked_to_and_faced():
    _, text = world(things={(2, -1): "tree"}, items={"wood": 1}, facing=(0, 1))
    assert "a tree 3 steps north-east" in text and "You face grass" in text
    costs = answer(text).costs
    assert best(text) in ("move north", "move east") and costs["move west"] > costs[best(text)]
    assert answer(text).plan[-1] == "interact"


def test_a_zombie_next_to_the_agent_is_faced_then_struck():
    env, text = world(things={(1, 0): objects.Zombie}, facing=(0, 1))
    assert "You face grass" in text and "a zombie 1 step east" in text
    assert best(text) == "move east" and answer(text).step.text == "fight the zombie"
    text = take(env, "move east")  # the zombie blocks: the move turns the agent to face it
    assert text.startswith("You face a zombie")
    assert best(text) == "interact"


def test_wood_and_a_table_nearby_make_a_wood_pickaxe_and_a_table_too_far_is_walked_to():
    env, text = world(things={(1, 1): "table"}, items={"wood": 3})
    assert "a table 2 steps south-east" in text  # diagonal: in crafter's 3x3 "nearby"
    assert best(text) == "make wood pickaxe"
    assert "1 wood pickaxe" in take(env, "make wood pickaxe")
    _, text = world(things={(0, 2): "table"}, items={"wood": 3})
    assert "a table 2 steps south" in text  # straight: not nearby
    assert best(text) == "move south" and answer(text).step.near == ("table",)
    _, text = world(items={"wood": 3})  # no table in view: place one (any ground faced will do)
    assert best(text) == "place table"


def test_thirst_with_water_faced_drinks():
    env, text = world(things={(0, 1): "water"}, facing=(0, 1), items={"drink": 2, "wood pickaxe": 1})
    assert text.startswith("You face water") and "drink 2/9" in text
    assert best(text) == "interact" and answer(text).step.text == "drink water"
    assert "drink 3/9" in take(env, "interact")


def test_a_stone_between_the_agent_and_coal_is_dug_through():
    _, text = world(things={(-1, 0): "stone", (-2, 0): "coal", (0, 1): "stone"}, facing=(-1, 0),
                    items={"wood pickaxe": 1, "wood": 1})
    assert text.startswith("You face stone; You see stone 1 step west, coal 2 steps west")
    assert best(text) == "interact"


def test_nothing_of_interest_in_view_explores_in_a_straight_line():
    items = {"wood": 5, "wood pickaxe": 1, "wood sword": 1}
    env, text = world(items=items)
    assert "You see" not in text
    first = answer(text)
    assert first.step.heading is not None and first.step.text == "find stone"
    move = best(text)
    assert move.startswith("move ") and all(first.costs[a] > first.costs[move] for a in first.costs if a != move)
    assert set(first.plan) == {move} and len(first.plan) >= 4
    assert best(take(env, move)) == move  # the same inventory and vitals: the same way on
    assert best(text, history=[(text, "move north")]) == "move north"  # with a history, the last move goes on


def test_lava_and_the_edge_of_the_world_are_never_walked_into():
    _, text = world(things={(-1, 0): "lava", (-3, 0): "tree"}, items={"wood": 1}, facing=(0, 1))
    assert "lava 1 step west" in text and "a tree 3 steps west" in text
    costs = answer(text).costs
    assert costs["move west"] == UNREACHABLE and best(text) in ("move north", "move south")
    env = make_env(ENV)
    env.reset(seed=0)
    game = env.unwrapped._env
    game._world.move(game._player, (0, 32))
    game._player.facing = (0, 1)
    text = crafter_text.render_text(game)
    assert "the edge of the world 1 step west" in text
    view = crafter_reading.parse_view(text)
    assert view.beyond_edge((-1, 0)) and view.beyond_edge((-4, 3)) and not view.beyond_edge((0, -3))
    for items in ({"wood": 5, "wood pickaxe": 1}, {"stone": 2, "wood pickaxe": 1}, {"wood": 1}, {}):
        game._player.inventory.update({k.replace(" ", "_"): v for k, v in items.items()})
        assert best(crafter_text.render_text(game)) != "move west"


def test_texts_and_refusals():
    _, text = world(things={(2, -1): "tree", (-3, 0): objects.Zombie}, items={"wood": 1, "health": 3})
    scene = parse_prompt(prompt(text))
    summary = ORACLE.text(scene, "summary")
    assert summary.startswith("The agent must collect wood. A tree is 3 steps north-east.")
    assert "A zombie is 3 steps west." in summary and "It has 1 wood." in summary and "Its health is low." in summary
    assert ORACLE.text(scene, "goal").startswith("collect wood, place a table, make a wood pickaxe")
    plan = ORACLE.text(scene, "plan").split(", ")
    assert set(plan) <= set(crafter_text.ACTION_NAMES) and plan[-1] == "interact"
    for bad in ("You see a red ball 2 steps forward", "You face grass; You have 2 rubies; Health 9/9, food 9/9, "
                "drink 9/9, energy 9/9"):
        with pytest.raises(UsageError, match=r"the Crafter oracle reads crafter-text@2 observations") as e:
            ORACLE.costs(Scene("Crafter", crafter_text.MISSION, (), bad, crafter_text.ACTION_NAMES))
        assert "\n" not in str(e.value)


# --- through the oracle backend --------------------------------------------------------------------
def test_the_backend_ranks_by_the_state_and_noise_one_answers_at_random_in_the_grammar():
    states = [world(things={(0, 1): "tree"})[1], world(things={(1, 0): objects.Zombie})[1],
              world(things={(1, 1): "table"}, items={"wood": 3})[1], world(items={"wood": 3})[1],
              world(things={(-2, 0): "water"}, items={"drink": 2})[1]]
    lm, noisy = OracleBackend("oracle"), OracleBackend("oracle:noise=1")
    prompts = [BUILDER.render("action", StateRecord(crafter_text.MISSION, (), t, crafter_text.ACTION_NAMES))
               for t in states]
    texts, candidates = [p.text for p in prompts], [list(p.candidates) for p in prompts]
    chosen = [p.candidates[s.best].strip() for p, s in zip(prompts, lm.score(texts, candidates))]
    assert chosen == ["interact", "move east", "make wood pickaxe", "place table", "move west"]
    randomly = [p.candidates[s.best].strip() for p, s in zip(prompts, noisy.score(texts, candidates))]
    assert randomly != chosen
    steps = set(ORACLE.text(parse_prompt(prompt(t)), "goal").split(", ")[0] for t in states)
    assert len(steps) == 5  # five states, five steps at hand
    rng = random.Random(0)
    vocabulary = set(crafter_text.ACTION_NAMES)
    for _ in range(50):
        scene = parse_prompt(prompt(states[0]))
        assert set(ORACLE.random_text(scene, "plan", rng).split(", ")) <= vocabulary
        goal = ORACLE.random_text(scene, "goal", rng).split(", ")
        verbs = ("make", "place", "find", "collect", "sleep")
        assert all(g in crafter_planner.STRIKES.values() or g.split()[0] in verbs for g in goal)
        assert ORACLE.random_text(scene, "summary", rng).startswith("The agent must ")
    record = StateRecord(crafter_text.MISSION, (), states[0], crafter_text.ACTION_NAMES)
    text_prompts = [BUILDER.render(task, record).text for task in ("summary", "goal", "plan")]
    said = [g.text for g in noisy.generate(text_prompts)]
    assert said[0].startswith("The agent must ") and set(said[2].split(", ")) <= vocabulary
    assert said != [ORACLE.text(parse_prompt(p), task) for p, task in zip(text_prompts, ("summary", "goal", "plan"))]


# --- playing --------------------------------------------------------------------------------------
def test_the_oracle_plays_a_seeded_episode_up_the_achievement_tree():
    env = make_env(ENV, length=120)
    _, info = env.reset(seed=2002)
    done = False
    while not done:
        _, _, term, trunc, info = env.step(ACTION[best(info["text"])])
        done = term or trunc
    unlocked = {k for k, v in info["achievements"].items() if v}
    assert {"collect_wood", "place_table", "make_wood_pickaxe", "collect_stone", "make_stone_pickaxe"} <= unlocked
