"""What the Crafter oracle's planner (`illm_tools.oracles.crafter_planner`) reads: one Crafter-Text
observation (`illm_tools.envs.crafter_text`, renderer crafter-text@2) as a `View`, and what the view
says about each cell around the agent.

The grammar, sentences joined by "; ": "You are sleeping" (only while asleep), "You face <thing>",
"You see <thing> <N> step(s) <direction>, ..." (each kind of thing of interest once, by its nearest
instance; left out when none is in view), "You have <count> <item>, ..." or "You have nothing",
"Health h/9, food f/9, drink d/9, energy e/9". The names below are crafter_text's (`_MATERIALS`,
`_OBJECTS`, `_SIGHT_ORDER`, `_COUNTABLE_ITEMS`, `ACTION_NAMES`), written out because this package sits
below `envs/` and cannot import it; tests/test_oracle_crafter.py checks that they agree.

Geometry (crafter's): x grows east, y grows SOUTH; the agent stands at (0, 0) and sees dx in [-4, 4],
dy in [-3, 3]. "N steps <direction>" is the Manhattan distance and a compass point, diagonal when the
smaller of |dx|, |dy| is at least half the larger: "3 steps north-east" is (1, -2) or (2, -1), so a
thing's place is a set of candidate cells (`Seen.cells`). What the text also tells, and `View.kinds`
works out for every cell: a kind not named is nowhere in view; no instance of a named kind is nearer
than the named one; between instances at one distance the faced one, else the northern-most, then the
western-most is named, so the cells at that distance before it (in that order) are not of its kind;
the edge of the world is a straight border, so every cell past its named one is out of the map.
"""
from __future__ import annotations

import functools
import re
from dataclasses import dataclass

from illm_tools.errors import UsageError

RENDERER = "crafter-text@2"
"""The renderer whose text this module reads (crafter_text's RENDERER_NAME@RENDERER_VERSION)."""
HALF_VIEW = (4, 3)
"""The view's reach east-west and north-south (crafter's 9x7 local view, centred on the agent)."""

SIGHT_ORDER = ("a zombie", "a skeleton", "an arrow", "lava", "a cow", "a ripe plant", "a plant", "water",
               "a tree", "stone", "coal", "iron", "a diamond", "a table", "a furnace", "the edge of the world")
"""crafter_text._SIGHT_ORDER: the kinds "You see" names."""
FACE_PHRASES = {
    "the edge of the world": "edge", "water": "water", "grass": "grass", "stone": "stone", "a path": "path",
    "sand": "sand", "a tree": "tree", "lava": "lava", "coal": "coal", "iron": "iron", "a diamond": "diamond",
    "a table": "table", "a furnace": "furnace", "a zombie": "zombie", "a skeleton": "skeleton",
    "an arrow": "arrow", "a cow": "cow", "a plant": "plant", "a ripe plant": "ripe plant"}
"""crafter_text._MATERIALS' and _OBJECTS' phrases (and "a ripe plant") -> the kind this module calls it."""
KINDS = tuple(FACE_PHRASES[p] for p in SIGHT_ORDER)
"""The kinds "You see" names, in the renderer's order."""
ITEMS = ("sapling", "wood", "stone", "coal", "iron", "diamond", "wood pickaxe", "stone pickaxe", "iron pickaxe",
         "wood sword", "stone sword", "iron sword")
"""crafter's items less the vitals, in its order, in words."""
COUNTABLE = ("sapling", "diamond", "wood pickaxe", "stone pickaxe", "iron pickaxe", "wood sword", "stone sword",
             "iron sword")
"""crafter_text._COUNTABLE_ITEMS: the items written with a plural "s" above one."""
VITALS = ("health", "food", "drink", "energy")
ACTIONS = ("do nothing", "move west", "move east", "move north", "move south", "interact", "sleep", "place stone",
           "place table", "place furnace", "place plant", "make wood pickaxe", "make stone pickaxe",
           "make iron pickaxe", "make wood sword", "make stone sword", "make iron sword")
"""crafter_text.ACTION_NAMES."""
STEPS = {"move west": (-1, 0), "move east": (1, 0), "move north": (0, -1), "move south": (0, 1)}
"""The moves, as offsets (y grows south)."""
GROUND = ("grass", "sand", "path")
"""What the agent walks on (crafter's walkable; the text never names it in "You see")."""

Cell = tuple[int, int]


def direction(dx: int, dy: int) -> str:
    """The compass point of an offset (dy > 0 is south): diagonal when the smaller side is at least half
    the larger. The renderer writes with it (`illm_tools.envs.crafter_text`), the oracle reads with it."""
    north_south = "north" if dy < 0 else "south"
    east_west = "east" if dx > 0 else "west"
    if 2 * min(abs(dx), abs(dy)) >= max(abs(dx), abs(dy)):
        return f"{north_south}-{east_west}"
    return east_west if abs(dx) > abs(dy) else north_south


def in_view(cell: Cell) -> bool:
    return abs(cell[0]) <= HALF_VIEW[0] and abs(cell[1]) <= HALF_VIEW[1]


@functools.lru_cache(maxsize=None)
def candidates(dist: int, where: str) -> tuple[Cell, ...]:
    """The cells in view `dist` steps away in the compass direction `where`."""
    xs, ys = range(-HALF_VIEW[0], HALF_VIEW[0] + 1), range(-HALF_VIEW[1], HALF_VIEW[1] + 1)
    return tuple((dx, dy) for dx in xs for dy in ys
                 if abs(dx) + abs(dy) == dist and dist and direction(dx, dy) == where)


@dataclass(frozen=True)
class Seen:
    """The nearest instance of a kind in view: its distance, compass point and candidate cells."""

    kind: str
    dist: int
    where: str
    cells: tuple[Cell, ...]

    @property
    def phrase(self) -> str:
        return f"{self.dist} {'step' if self.dist == 1 else 'steps'} {self.where}"


@dataclass(frozen=True)
class View:
    """One observation: asleep, the faced thing, what is in view, the inventory, the vitals."""

    sleeping: bool
    facing: str
    """The faced thing's kind ("tree", "grass", "edge", ...)."""
    seen: dict[str, Seen]
    items: dict[str, int]
    vitals: dict[str, int]

    def has(self, item: str, count: int = 1) -> bool:
        return self.items.get(item, 0) >= count

    def near(self, kind: str) -> bool:
        """Whether an instance of `kind` lies in the 3x3 cells around the agent (crafter's "nearby"
        for crafting: `world.nearby(pos, 1)`): 1 step away, or 2 steps on a diagonal."""
        seen = self.seen.get(kind)
        return seen is not None and all(max(abs(x), abs(y)) <= 1 for x, y in seen.cells)

    @functools.cached_property
    def facing_cell(self) -> Cell | None:
        """The faced cell when the text tells it: the faced thing is of a kind "You see" names, and then
        the named instance at 1 step is the faced one (the faced instance wins ties)."""
        seen = self.seen.get(self.facing)
        return seen.cells[0] if seen is not None and seen.dist == 1 else None

    @functools.cached_property
    def kinds(self) -> dict[Cell, tuple[str | None, frozenset[str]]]:
        """Every cell in view but the agent's -> (its kind when the text tells it, the kinds it may be)."""
        out: dict[Cell, tuple[str | None, frozenset[str]]] = {}
        for dx in range(-HALF_VIEW[0], HALF_VIEW[0] + 1):
            for dy in range(-HALF_VIEW[1], HALF_VIEW[1] + 1):
                if (dx, dy) != (0, 0):
                    out[(dx, dy)] = self._kinds_at((dx, dy))
        return out

    def beyond_edge(self, cell: Cell) -> bool:
        """Whether a cell lies past the map's border: the named edge cell is straight along an axis,
        and the border is a straight line through it."""
        edge = self.seen.get("edge")
        if edge is None or len(edge.cells) != 1:
            return False
        (ex, ey), (x, y) = edge.cells[0], cell
        return (ex != 0 and x * ex >= ex * ex) or (ey != 0 and y * ey >= ey * ey)

    def _kinds_at(self, cell: Cell) -> tuple[str | None, frozenset[str]]:
        if self.beyond_edge(cell):
            return "edge", frozenset(("edge",))
        r = abs(cell[0]) + abs(cell[1])
        maybe = set()
        for kind, seen in self.seen.items():
            if kind == "edge":
                continue
            if r < seen.dist:
                continue
            if r == seen.dist:
                if seen.cells == (cell,):
                    return kind, frozenset((kind,))
                first = min((y, x) for x, y in seen.cells)
                if kind != self.facing and (cell[1], cell[0]) < first:
                    continue  # it would have been named instead
            maybe.add(kind)
        return None, frozenset(maybe)


_SIGHT = re.compile(r"^(?P<phrase>.+?) (?P<dist>\d+) steps? (?P<where>(?:north|south)(?:-(?:east|west))?|east|west)$")
_VITALS = re.compile(r"^Health (\d+)/9, food (\d+)/9, drink (\d+)/9, energy (\d+)/9$")
_ITEM = re.compile(r"^(\d+) (.+)$")
_SIGHT_KINDS = dict(zip(SIGHT_ORDER, KINDS))


def _bad(text: str, why: str) -> UsageError:
    return UsageError(f"the Crafter oracle reads {RENDERER} observations and cannot read {text[:80]!r} ({why})")


@functools.lru_cache(maxsize=65536)
def parse_view(text: str) -> View:
    """The `View` of one Crafter-Text observation; text of another grammar is refused in one line."""
    sentences = [s.strip() for s in text.strip().split("; ")]
    sleeping = bool(sentences) and sentences[0] == "You are sleeping"
    rest = sentences[1:] if sleeping else sentences
    if len(rest) not in (3, 4) or not rest[0].startswith("You face "):
        raise _bad(text, "expected 'You face ...; [You see ...; ]You have ...; Health ...'")
    facing = FACE_PHRASES.get(rest[0][len("You face "):])
    if facing is None:
        raise _bad(text, f"unknown faced thing {rest[0][len('You face '):]!r}")
    seen: dict[str, Seen] = {}
    if len(rest) == 4:
        if not rest[1].startswith("You see "):
            raise _bad(text, "expected 'You see ...'")
        for part in rest[1][len("You see "):].split(", "):
            m = _SIGHT.match(part)
            kind = _SIGHT_KINDS.get(m.group("phrase")) if m else None
            if kind is None:
                raise _bad(text, f"unknown sight {part!r}")
            dist = int(m.group("dist"))
            seen[kind] = Seen(kind, dist, m.group("where"), candidates(dist, m.group("where")))
    have, vitals = rest[-2], _VITALS.match(rest[-1])
    if not have.startswith("You have ") or vitals is None:
        raise _bad(text, "expected 'You have ...; Health h/9, food f/9, drink d/9, energy e/9'")
    items: dict[str, int] = {}
    if have != "You have nothing":
        for part in have[len("You have "):].split(", "):
            m = _ITEM.match(part)
            name = m.group(2) if m else ""
            if m and name not in ITEMS and name.endswith("s") and name[:-1] in COUNTABLE:
                name = name[:-1]
            if name not in ITEMS:
                raise _bad(text, f"unknown item {part!r}")
            items[name] = int(m.group(1))
    return View(sleeping, facing, seen, items, dict(zip(VITALS, (int(v) for v in vitals.groups()))))
