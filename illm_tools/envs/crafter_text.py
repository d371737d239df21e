"""Crafter-Text: the text renderer for Crafter (Hafner 2021, the `crafter` package) states, its action
names, and the Crafter score.

Crafter's world is indexed [x, y] with x growing to the east (right in the image) and y growing to
the SOUTH (down in the image): `move_up` is (0, -1). The agent sees the 9x7 cells of the map around
it (`env._local_view`, the 9x9 image less its two inventory rows), centred on itself; it faces
`player.pos + player.facing`. `describe` reads the world, not the image, and returns these
sentences in this order:

1. "You are sleeping", only while the agent sleeps (the image is then greyed but still shows the map).
2. "You face <thing>": the creature or object in the cell the agent faces, else its material
   ("You face a tree", "You face water", "You face grass", "You face a zombie"); "the edge of the
   world" outside the map.
3. "You see <thing> <N> step(s) <direction>, ...": every kind of thing of interest in the 9x7 view,
   each named once by its nearest instance, nearest first. Things of interest are the creatures and
   objects (zombie, skeleton, arrow, cow, plant, ripe plant), the materials water, stone, coal, iron,
   diamond, tree, lava, table and furnace, and the edge of the world (the cells past the map's
   border, which the image shows grey: "the edge of the world 2 steps west", renderer version 2;
   its nearest cell is straight along one axis, so the whole row or column from there on is out);
   the ground (grass, sand, path) and the agent are not described. N is the Manhattan distance (the
   moves needed on an open floor). <direction> is one of the eight compass points: a diagonal one
   when the smaller of |dx|, |dy| is at least half the larger, else the larger's axis ("a cow 4
   steps east" for dx=3, dy=1). Ties in distance go by the kind order of `_SIGHT_ORDER`; between
   instances of one kind, the faced one, else the northern-most, then the western-most wins. The
   sentence is left out when nothing of interest is in view.
4. "You have 2 wood, 1 wood pickaxe": the inventory items with a count above 0 in crafter's item
   order (vitals excluded; saplings, diamonds, pickaxes and swords take a plural "s"), or "You have
   nothing".
5. "Health 9/9, food 8/9, drink 7/9, energy 9/9": the vitals out of their maximum.

`render_text` joins them with "; " (sentences 3 to 5 contain commas themselves). The text ignores
daylight: at night crafter's image darkens and blurs the view's edges, the text still names all of it.

Actions are named by compass direction to match the text: crafter's move_left/right/up/down are
"move west/east/north/south"; `do` (collect the faced material, drink faced water, eat a ripe
plant, attack a creature) is "interact"; noop is "do nothing".

CHANGING THE RENDERED TEXT IN ANY WAY MUST BUMP `RENDERER_VERSION`: "crafter-text@<version>" goes
into every annotation cache key, so a changed renderer with an unchanged version would silently
serve annotations of other texts.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from typing import Any

from crafter import constants

from illm_tools.errors import UsageError
from illm_tools.oracles.crafter_reading import direction as _direction  # one rule for the text and its reader

RENDERER_NAME = "crafter-text"
RENDERER_VERSION = 2
"""1: no edge of the world in "You see"; 2: the nearest cell past the map's border is named there too
(a player who cannot see the border walks into it and stays: the image shows it, the text did not)."""

# Crafter's 17 actions (crafter.constants.actions), in its order, in words.
_ACTION_WORDS = {
    "noop": "do nothing", "move_left": "move west", "move_right": "move east", "move_up": "move north",
    "move_down": "move south", "do": "interact", "sleep": "sleep",
}
ACTION_NAMES: tuple[str, ...] = tuple(_ACTION_WORDS.get(name, name.replace("_", " ")) for name in constants.actions)
ACHIEVEMENTS: tuple[str, ...] = tuple(constants.achievements)
MISSION = "survive, collect resources and craft tools to unlock as many achievements as possible"

_VITALS = ("health", "food", "drink", "energy")
_MATERIALS = {
    None: "the edge of the world", "water": "water", "grass": "grass", "stone": "stone", "path": "a path",
    "sand": "sand", "tree": "a tree", "lava": "lava", "coal": "coal", "iron": "iron", "diamond": "a diamond",
    "table": "a table", "furnace": "a furnace",
}
_OBJECTS = {"Zombie": "a zombie", "Skeleton": "a skeleton", "Arrow": "an arrow", "Cow": "a cow", "Plant": "a plant"}
# Kinds described by sentence 3, by name phrase; their order breaks ties in distance.
_SIGHT_ORDER = ("a zombie", "a skeleton", "an arrow", "lava", "a cow", "a ripe plant", "a plant", "water",
                "a tree", "stone", "coal", "iron", "a diamond", "a table", "a furnace", "the edge of the world")
_SIGHT_RANK = {phrase: rank for rank, phrase in enumerate(_SIGHT_ORDER)}
_COUNTABLE_ITEMS = ("sapling", "diamond", "wood_pickaxe", "stone_pickaxe", "iron_pickaxe", "wood_sword",
                    "stone_sword", "iron_sword")


@functools.lru_cache(maxsize=16)
def _view_offsets(width: int, height: int, facing: tuple[int, int]) -> tuple[tuple[int, int, int], ...]:
    """(distance, dx, dy) of every cell of a width x height view around the agent but its own (crafter's
    LocalView centre: grid // 2), nearest first, then the faced cell, then north to south, then west to
    east."""
    cx, cy = width // 2, height // 2
    cells = [(abs(dx) + abs(dy), (dx, dy) != facing, dy, dx)
             for dx in range(-cx, width - cx) for dy in range(-cy, height - cy)]
    return tuple((dist, dx, dy) for dist, _, dy, dx in sorted(cells) if dist)




def _object(obj: Any) -> str:
    name = type(obj).__name__
    if name == "Plant" and obj.ripe:
        return "a ripe plant"
    return _OBJECTS[name]


def _thing(material: str | None, obj: Any) -> str:
    """The creature or object (plant, arrow) in a cell, else its material."""
    return _object(obj) if obj is not None else _MATERIALS[material]


def _item(name: str, count: int) -> str:
    words = name.replace("_", " ")
    return f"{count} {words}s" if count > 1 and name in _COUNTABLE_ITEMS else f"{count} {words}"


def _sight(env: Any) -> str | None:
    """Sentence 3: the nearest instance of each kind of thing of interest in view, or None."""
    world, player = env._world, env._player
    width, height = (int(n) for n in env._local_view._grid)
    px, py = int(player.pos[0]), int(player.pos[1])
    nearest: dict[str, tuple[int, int, int]] = {}
    facing = (int(player.facing[0]), int(player.facing[1]))
    for dist, dx, dy in _view_offsets(width, height, facing):
        material, obj = world[px + dx, py + dy]
        for phrase in (_MATERIALS[material], None if obj is None else _object(obj)):
            if phrase in _SIGHT_RANK and phrase not in nearest:
                nearest[phrase] = (dist, dx, dy)
    if not nearest:
        return None
    ordered = sorted(nearest.items(), key=lambda item: (item[1][0], _SIGHT_RANK[item[0]]))
    return "You see " + ", ".join(
        f"{phrase} {dist} {'step' if dist == 1 else 'steps'} {_direction(dx, dy)}"
        for phrase, (dist, dx, dy) in ordered)


def describe(env: Any) -> list[str]:
    """The Crafter-Text sentences for the current state of a `crafter.Env` (after reset() or step())."""
    player = env._player
    sentences = ["You are sleeping"] if player.sleeping else []
    sentences.append(f"You face {_thing(*env._world[player.pos + player.facing])}")
    sight = _sight(env)
    if sight:
        sentences.append(sight)
    items = [_item(name, count) for name, count in player.inventory.items() if name not in _VITALS and count > 0]
    sentences.append("You have " + (", ".join(items) if items else "nothing"))
    vitals = ", ".join(f"{name} {player.inventory[name]}/{constants.items[name]['max']}" for name in _VITALS)
    sentences.append(vitals.capitalize())
    return sentences


def render_text(env: Any) -> str:
    """The Crafter-Text description of the env's current state: `describe`'s sentences joined with "; "."""
    return "; ".join(describe(env))


def achievement_success_rates(episodes: Sequence[Mapping[str, int]]) -> dict[str, float]:
    """For every achievement, the fraction (0..1) of episodes that unlocked it at least once, from each
    episode's final `info['achievements']` (counts by crafter's names; a missing name counts 0)."""
    if not episodes:
        raise UsageError("no episodes to compute Crafter success rates from")
    for episode in episodes:
        unknown = sorted(set(episode) - set(ACHIEVEMENTS))
        if unknown:
            raise UsageError(f"unknown Crafter achievement(s) {', '.join(unknown)}; expected crafter's names "
                             f"such as {ACHIEVEMENTS[0]} (without an 'achievement_' prefix)")
    return {name: sum(episode.get(name, 0) > 0 for episode in episodes) / len(episodes) for name in ACHIEVEMENTS}


def crafter_score(success_rates: Mapping[str, float]) -> float:
    """The Crafter score of Hafner (2021), in percent: exp(mean_i ln(1 + s_i)) - 1 over all 22
    achievements, s_i the success rate of achievement i IN PERCENT (0..100), as crafter's own
    `compute_scores` takes them: multiply `achievement_success_rates`' fractions by 100."""
    missing = [name for name in ACHIEVEMENTS if name not in success_rates]
    unknown = sorted(set(success_rates) - set(ACHIEVEMENTS))
    if missing or unknown:
        raise UsageError(f"the Crafter score needs the success rate of exactly the {len(ACHIEVEMENTS)} achievements; "
                         f"missing: {', '.join(missing) or 'none'}; unknown: {', '.join(unknown) or 'none'}")
    bad = {name: rate for name, rate in success_rates.items() if not 0.0 <= rate <= 100.0}
    if bad:
        raise UsageError(f"success rates must be percentages in 0..100, got {bad}")
    log_sum = sum(math.log1p(success_rates[name]) for name in ACHIEVEMENTS)
    return math.exp(log_sum / len(ACHIEVEMENTS)) - 1.0
