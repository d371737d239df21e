"""MiniHack-Text: the text illm writes for a MiniHack (NetHack Learning Environment) observation,
and the missions of the paper's MiniHack tasks (readable names for NLE's actions: `minihack_actions`).

The text is `describe`'s phrases joined with "; " (NetHack's messages and the inventory list
contain commas, so a comma cannot separate phrases). Phrases, in this order:

1. "message: <text>": NetHack's message line (`message`), whitespace collapsed; left out when empty.
2. "you are <state> and <state>": the status conditions NetHack's bottom line shows
   (`blstats` condition mask: levitating, flying, riding, blind, deaf, stunned, confused,
   hallucinating, sick from food poisoning, terminally ill, turning to stone, turning into slime,
   being strangled); "your hit points are low (<hp> of <max>)" when hit points are at most 5 or
   at most a seventh of the maximum (NetHack's own "low hit points" rule, the one prayer answers).
3. What the map (`glyphs`; the agent stands at x = blstats[0], y = blstats[1]) shows, as
   "<thing> <distance> <direction> (<offset>)", e.g. "a newt very near east (2 east)", "lava
   adjacent east (1 east)", "2 boulders far northeast (5 east, 3 north)", "the staircase down very
   far east (11 east, 1 south)"; the offset is the nearest square's of the phrase, in squares east
   or west and north or south (version 2: a band and a direction alone do not say where to step,
   so neither a planner nor an LLM could walk to a thing more than a square away). Things are monsters (a pet is
   "a tame little dog", a remembered unseen monster "an unseen creature"), objects, corpses,
   statues and dungeon features: doorways, doors, stairs, ladders, altars, fountains, sinks,
   thrones, graves, trees, iron bars, water, lava, ice, drawbridges, traps, poison clouds. Walls,
   floor, corridors, dark and unexplored parts, and transient effects (zaps, explosions, warnings,
   the inside of an engulfer) are not described; nor is the agent's own square (NetHack shows the
   agent there; what lies under it comes in the message, "You see here ...").
   - Direction: the nearest of the 8 compass directions to the angle from the agent (screen up is
     north); integer offsets never fall exactly between two directions.
   - Distance: by Chebyshev distance d (the number of moves, diagonals allowed): d = 1 "adjacent",
     2 "very near", 3-4 "near", 5-8 "far", 9 or more "very far".
   - Grouping: the squares of one thing in one distance band and one direction make one phrase,
     with its count ("3 boulders near east"); water, lava, ice, iron bars and gold take no count
     or article ("water far east"). Staircases, ladders and unique monsters take "the" ("the
     Oracle"), monsters with proper names no article ("Medusa"), the rest "a" or "an".
   - Names: monsters by NetHack's species name; objects as a player sees them before identifying
     them. NLE's object glyphs follow the looks NetHack shuffles each game (a ring of levitation
     that looks "opal" shows the glyph of the ring whose fixed look is "opal"), so the glyph's
     object name is wrong for those: potions, rings, wands, scrolls, spellbooks and amulets are
     named by their class ("a ring"), the shuffled helmets, cloaks, gloves and boots by their kind
     ("a pair of boots"); gems by colour ("a red gem", "a gray stone"); everything else by its
     fixed look or, when it has none, its name ("a boulder", "a horn", "a runed dagger"). Class
     names rather than looks keep the text the same across episodes.
   - Offset: "<n> east" or "<n> west", then "<n> north" or "<n> south", each left out when 0.
   - Selection: at most 3 phrases per thing (its nearest), then at most 12 in all, chosen
     staircases and ladders down first (the goal of most MiniHack tasks), then monsters and
     objects, then the other features, nearer first within each; the chosen phrases are written
     nearest first, ties broken clockwise from north, then by name.
4. "walls adjacent <direction>, <direction> and <direction>" ("a wall adjacent north" for one): the
   agent's neighbouring squares that are walls (version 2: walls are otherwise not described, and
   without them a step into one is the only way to learn where a room ends).
5. "you carry <item>, <item>": NetHack's inventory lines (`inv_strs`) of what the agent carries
   beyond the starting kits of MiniHack's default characters (a rogue in navigation tasks: short
   sword, daggers, leather armor, potion of sickness, lock pick, sack, at times a blindfold; a
   caveman in skill tasks: club, sling, flint stones, rocks, leather armor; a kit item is a line
   naming only it, its count, curse status, erosion, enchantment and state, e.g. "17 uncursed flint
   stones (in quiver pouch)", "an uncursed very burnt +1 leather armor (being worn)"), so that
   it says "you carry a ring of levitation (on right hand)" once the LavaCross ring is picked up
   and put on, and nothing while only the kit is carried. Left out when empty.

`describe` needs the observation keys in `OBS_KEYS`; make the env with
`gym.make(env_id, observation_keys=OBS_KEYS)` (plus whatever else the policy reads).

The paper's five MiniHack tasks (`TASKS`) and the ids minihack 1.0 registers for them:
- "River-Monster" -> MiniHack-River-Monster-v0;
- "MultiRoom-N4-Monster" -> MiniHack-MultiRoom-N4-Monster-v0;
- "LavaCross-Ring" -> MiniHack-LavaCross-Levitate-Ring-Pickup-Full-v0;
- "LavaCross-Potion" -> MiniHack-LavaCross-Levitate-Potion-Pickup-Full-v0;
- "LavaCross-Full" -> MiniHack-LavaCross-Full-v0.
minihack has no id without a "-Full"/"-Restricted" suffix for the ring and potion tasks: the suffix
is the action set (all of NLE's actions, or the few the task needs), not the task, while the "Full"
of "LavaCross-Full" is the task with every item (a levitation potion, ring or boots, a wand of cold
or a frost horn) and happens to use the full action set too. The ring and potion tasks take the
"-Full" ids so that all three LavaCross tasks share one action set. "Pickup" (the item lies on the
floor) rather than "Inv" (the agent starts carrying it).

CHANGING THE RENDERED TEXT IN ANY WAY MUST BUMP `RENDERER_VERSION`: "minihack-text@<version>" goes
into every annotation cache key, so a changed renderer with an unchanged version would silently
serve annotations of other texts.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
from nle import nethack  # no minihack import here: minihack's import warns (pkg_resources)

from illm_tools.envs.minihack_glyphs import _Thing, _glyph_table, _noun_phrase

RENDERER_NAME = "minihack-text"
RENDERER_VERSION = 2
"""Part of every annotation cache key: CHANGING THE RENDERED TEXT MUST BUMP IT."""

OBS_KEYS: tuple[str, ...] = ("glyphs", "message", "blstats", "inv_strs")

TASKS: dict[str, str] = {
    "River-Monster": "MiniHack-River-Monster-v0",
    "MultiRoom-N4-Monster": "MiniHack-MultiRoom-N4-Monster-v0",
    "LavaCross-Ring": "MiniHack-LavaCross-Levitate-Ring-Pickup-Full-v0",
    "LavaCross-Potion": "MiniHack-LavaCross-Levitate-Potion-Pickup-Full-v0",
    "LavaCross-Full": "MiniHack-LavaCross-Full-v0",
}
"""The paper's task names -> MiniHack env ids (see the module docstring for the choice of ids)."""

# Goals read off minihack's env classes and level files, first matching prefix wins.
_MISSIONS: tuple[tuple[str, str], ...] = (
    ("MiniHack-River", "cross the river by pushing boulders into it, and reach the staircase down"),
    ("MiniHack-MultiRoom-", "go through the rooms and their doors to reach the staircase down"),
    ("MiniHack-LavaCross-Levitate-Ring-Inv",
     "put on the ring of levitation you carry, float over the lava and reach the staircase down"),
    ("MiniHack-LavaCross-Levitate-Ring",
     "pick up the ring of levitation, put it on, float over the lava and reach the staircase down"),
    ("MiniHack-LavaCross-Levitate-Potion-Inv",
     "drink the potion of levitation you carry, float over the lava and reach the staircase down"),
    ("MiniHack-LavaCross-Levitate-Potion",
     "pick up the potion of levitation, drink it, float over the lava and reach the staircase down"),
    ("MiniHack-LavaCross-Levitate",
     "pick up the levitation item (a potion, ring or boots), use it to float over the lava, "
     "and reach the staircase down"),
    ("MiniHack-LavaCross",
     "pick up the item on your side of the lava (a levitation potion, ring or boots, a wand of cold "
     "or a frost horn), use it to cross the lava, and reach the staircase down"),
    ("MiniHack-LavaCrossing", "get past the lava to reach the staircase down"),
    ("MiniHack-Eat", "eat the apple"),
    ("MiniHack-Wield", "wield the dagger"),
    ("MiniHack-Wear", "wear the robe"),
    ("MiniHack-PutOn", "put on the amulet"),
    ("MiniHack-Zap", "zap the wand"),
    ("MiniHack-Read", "read the scroll"),
    ("MiniHack-Pray", "pray at the altar"),
    ("MiniHack-Sink", "drink (quaff) from the sink"),
    ("MiniHack-LockedDoor", "kick open the locked door and reach the staircase down"),
    ("MiniHack-ClosedDoor", "open the closed door and reach the staircase down"),
    ("MiniHack-Freeze-Lava", "freeze the lava with cold and reach the staircase down"),
    ("MiniHack-Freeze", "shoot a bolt of cold that bounces off a wall"),
    ("MiniHack-Levitate", "start levitating with the levitation item"),
    ("MiniHack-WoD", "kill the minotaur with the wand of death"),
    ("MiniHack-Boxoban", "push every boulder onto a fountain"),
)
_DEFAULT_MISSION = "reach the staircase down"


def mission(env_id: str) -> str:
    """The goal of a MiniHack task in one short phrase, for LLM prompts; "reach the staircase down"
    (MiniHack's default goal) for tasks without a more specific one."""
    return next((text for prefix, text in _MISSIONS if env_id.startswith(prefix)), _DEFAULT_MISSION)


# ------------------------------------------------------------------------------------ map things

_DIRECTIONS = ("north", "northeast", "east", "southeast", "south", "southwest", "west", "northwest")
_MAX_MAP_PHRASES = 12
_MAX_PHRASES_PER_THING = 3

def _heading(dx: int, dy: int) -> int:
    """The compass direction (index into _DIRECTIONS) nearest to the offset (dx columns east, dy
    rows south) of a square."""
    angle = math.degrees(math.atan2(dx, -dy))  # 0 = north, clockwise
    return round(angle / 45) % 8


def _distance_band(distance: int) -> str:
    """The distance word for a Chebyshev distance of at least 1."""
    if distance <= 1:
        return "adjacent"
    if distance == 2:
        return "very near"
    if distance <= 4:
        return "near"
    return "far" if distance <= 8 else "very far"


@dataclass
class _Group:
    thing: _Thing
    band: str
    heading: int
    """Index into _DIRECTIONS."""
    distance: int
    """Of the group's nearest square."""
    offset: tuple[int, int]
    """(dx, dy) of the group's nearest square (the first met of equally near ones, in row order)."""
    count: int = 1

    def order(self) -> tuple[int, int, str]:
        return self.distance, self.heading, self.thing.name


def _map_phrases(glyphs: np.ndarray, x: int, y: int) -> list[str]:
    things, described = _glyph_table()
    glyphs = np.asarray(glyphs)
    mask = described[glyphs]
    mask[y, x] = False
    groups: dict[tuple[str, str, int], _Group] = {}
    for row, col in zip(*np.nonzero(mask)):
        thing = things[glyphs[row, col]]
        dx, dy = int(col) - x, int(row) - y
        distance = max(abs(dx), abs(dy))
        heading = _heading(dx, dy)
        key = (thing.name, _distance_band(distance), heading)
        if key in groups:
            group = groups[key]
            group.count += 1
            if distance < group.distance:
                group.distance, group.offset = distance, (dx, dy)
        else:
            groups[key] = _Group(thing, key[1], heading, distance, (dx, dy))
    per_thing: dict[str, int] = {}
    nearest = []
    for group in sorted(groups.values(), key=_Group.order):
        per_thing[group.thing.name] = per_thing.get(group.thing.name, 0) + 1
        if per_thing[group.thing.name] <= _MAX_PHRASES_PER_THING:
            nearest.append(group)
    chosen = sorted(nearest, key=lambda g: (g.thing.tier, *g.order()))[:_MAX_MAP_PHRASES]
    return [f"{_noun_phrase(g.thing, g.count)} {g.band} {_DIRECTIONS[g.heading]} ({_offset(*g.offset)})"
            for g in sorted(chosen, key=_Group.order)]


def _offset(dx: int, dy: int) -> str:
    """(3, -1) -> "3 east, 1 north"; a zero part is left out."""
    parts = [f"{abs(dx)} {'east' if dx > 0 else 'west'}" if dx else "",
             f"{abs(dy)} {'south' if dy > 0 else 'north'}" if dy else ""]
    return ", ".join(p for p in parts if p)


_WALL_CMAP = range(1, 12)
"""NetHack's defsyms 1-11: vertical and horizontal walls, the four corners, crosswall and T-walls."""
_NEIGHBOURS = ((0, -1), (1, -1), (1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1))
"""(dx, dy) of the 8 neighbours, clockwise from north (the order of _DIRECTIONS)."""


def _walls(glyphs: np.ndarray, x: int, y: int) -> list[str]:
    """The "walls adjacent ..." phrase of the agent's neighbouring wall squares, clockwise from north."""
    rows, cols = glyphs.shape
    found = []
    for heading, (dx, dy) in enumerate(_NEIGHBOURS):
        col, row = x + dx, y + dy
        if 0 <= row < rows and 0 <= col < cols:
            glyph = int(glyphs[row, col])
            if nethack.glyph_is_cmap(glyph) and nethack.glyph_to_cmap(glyph) in _WALL_CMAP:
                found.append(_DIRECTIONS[heading])
    if not found:
        return []
    if len(found) == 1:
        return [f"a wall adjacent {found[0]}"]
    return [f"walls adjacent {', '.join(found[:-1])} and {found[-1]}"]


# ------------------------------------------------------------------------- message, status, items

_CONDITIONS = (
    (nethack.BL_MASK_LEV, "levitating"), (nethack.BL_MASK_FLY, "flying"), (nethack.BL_MASK_RIDE, "riding"),
    (nethack.BL_MASK_BLIND, "blind"), (nethack.BL_MASK_DEAF, "deaf"), (nethack.BL_MASK_STUN, "stunned"),
    (nethack.BL_MASK_CONF, "confused"), (nethack.BL_MASK_HALLU, "hallucinating"),
    (nethack.BL_MASK_FOODPOIS, "sick from food poisoning"), (nethack.BL_MASK_TERMILL, "terminally ill"),
    (nethack.BL_MASK_STONE, "turning to stone"), (nethack.BL_MASK_SLIME, "turning into slime"),
    (nethack.BL_MASK_STRNGL, "being strangled"),
)
# An inventory line of the starting kits of MiniHack's default characters (rogue, caveman): the
# item's name with only its count, curse status, erosion, enchantment and state around it. Matched
# on the text: inventory glyphs follow shuffled looks, so the potion of sickness has no fixed glyph.
_KIT_ITEM = re.compile(
    r"(?:a|an|\d+)(?: (?:uncursed|cursed|blessed|empty|greased|poisoned|(?:fire|rust|corrode|rot)proof"
    r"|(?:very |thoroughly )?(?:burnt|rusty|corroded|rotted)|[+-]\d+))* "
    r"(?:short swords?|daggers?|leather armor|potions? of sickness|lock picks?|sacks?|blindfolds?|clubs?"
    r"|slings?|flint stones?|rocks?)(?: \(.*\))?")


def _decode(text: np.ndarray) -> str:
    """NUL-padded bytes -> text with runs of whitespace collapsed to one space."""
    raw = np.asarray(text, dtype=np.uint8).tobytes().split(b"\0", 1)[0]
    return " ".join(raw.decode("latin-1").split())


def _status(blstats: np.ndarray) -> list[str]:
    phrases = []
    condition = int(blstats[nethack.NLE_BL_CONDITION])
    states = [word for mask, word in _CONDITIONS if condition & mask]
    if states:
        phrases.append("you are " + " and ".join(states))
    hp, hp_max = int(blstats[nethack.NLE_BL_HP]), int(blstats[nethack.NLE_BL_HPMAX])
    if hp_max > 0 and (hp <= 5 or hp * 7 <= hp_max):
        phrases.append(f"your hit points are low ({hp} of {hp_max})")
    return phrases


def _carried(inv_strs: np.ndarray) -> list[str]:
    items = (_decode(text) for text in inv_strs)
    return [item for item in items if item and not _KIT_ITEM.fullmatch(item)]


def describe(obs: dict) -> list[str]:
    """The MiniHack-Text phrases for one observation (a dict holding `OBS_KEYS`), in the order of
    the module docstring: message, status, map (nearest first), walls, inventory."""
    blstats = np.asarray(obs["blstats"])
    phrases = []
    message = _decode(obs["message"])
    if message:
        phrases.append(f"message: {message}")
    phrases += _status(blstats)
    x, y = int(blstats[nethack.NLE_BL_X]), int(blstats[nethack.NLE_BL_Y])
    phrases += _map_phrases(obs["glyphs"], x, y)
    phrases += _walls(np.asarray(obs["glyphs"]), x, y)
    carried = _carried(obs["inv_strs"])
    if carried:
        phrases.append("you carry " + ", ".join(carried))
    return phrases


def render_text(obs: dict) -> str:
    """The MiniHack-Text description of one observation: `describe`'s phrases joined with "; "."""
    return "; ".join(describe(obs))
