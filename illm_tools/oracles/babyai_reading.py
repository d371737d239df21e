"""What the BabyAI oracle's planner reads (`illm_tools.oracles.babyai_planner`), beyond the prompt's
frame (`illm_tools.oracles.base.parse_prompt`: game, mission, the numbered observations and actions,
the valid actions, as a `Scene`): each observation's BabyAI-Text sentences as a `View` of `Thing`s,
and the mission as its instructions (`Instr`, `Desc`). Split from the planner along the seam
between reading text and planning on it; the planner re-exports these names.
"""
from __future__ import annotations

import functools
import re
from dataclasses import dataclass

COLOURS = ("red", "green", "blue", "purple", "yellow", "grey")

# --- what the prompt says ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Thing:
    """An object in view, `x` columns right of the agent (negative: left) and `y` rows ahead."""

    kind: str
    colour: str
    state: str
    """Doors: open, closed or locked; "" otherwise."""
    x: int
    y: int

    @property
    def name(self) -> str:
        return f"{self.colour} {self.kind}"


@dataclass(frozen=True)
class View:
    """One observation: the objects in view, the first wall on each ray, what the agent carries."""

    things: tuple[Thing, ...]
    walls: tuple[int | None, int | None, int | None]
    """Distance to the first wall forward, left and right (None: the ray met none)."""
    carrying: tuple[str, str] | None
    """(colour, kind) of the carried object."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "_cells", {(t.x, t.y): t for t in self.things})

    def at(self, x: int, y: int) -> Thing | None:
        return self._cells.get((x, y))  # type: ignore[attr-defined]


_SEE = re.compile(r"^You see (?:a|an) (?:(open|closed|locked) )?(\w+) (\w+) (.+)$")
_WALL = re.compile(r"^You see a wall (\d+) steps? (forward|left|right)$")
_CARRY = re.compile(r"^You carry (?:a|an) (\w+) (\w+)$")
_LOC = re.compile(r"^(?:(\d+) steps? (left|right))?(?: and )?(?:(\d+) steps? forward)?$")


@functools.lru_cache(maxsize=65536)
def parse_view(text: str) -> View:
    """The objects, walls and carried object of one BabyAI-Text observation."""
    things, walls, carrying = [], [None, None, None], None
    for sentence in re.split(r", (?=You )", text.strip()):
        sentence = sentence.strip()
        if not sentence or sentence == "nothing":
            continue
        if m := _WALL.match(sentence):
            walls[("forward", "left", "right").index(m.group(2))] = int(m.group(1))
        elif m := _CARRY.match(sentence):
            carrying = (m.group(1), m.group(2))
        elif m := _SEE.match(sentence):
            state, colour, kind, where = m.groups()
            loc = _LOC.match(where)
            if loc is None:
                continue
            side, direction, ahead = loc.groups()
            x = 0 if side is None else int(side) * (1 if direction == "right" else -1)
            things.append(Thing(kind, colour, state or "", x, int(ahead or 0)))
    return View(tuple(things), (walls[0], walls[1], walls[2]), carrying)


# --- missions ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Desc:
    """An object description of a mission: kind (None: any object) and colour (None: any)."""

    kind: str | None
    colour: str | None = None

    def matches(self, kind: str, colour: str) -> bool:
        return (self.kind is None or self.kind == kind) and (self.colour is None or self.colour == colour)

    @property
    def text(self) -> str:
        return " ".join(filter(None, ("the", self.colour, self.kind or "object")))


@dataclass(frozen=True)
class Instr:
    """One instruction: verb goto | pickup | open | putnext | enter, its object, and for putnext the
    object to put it next to."""

    verb: str
    obj: Desc
    near: Desc | None = None

    @property
    def text(self) -> str:
        if self.verb == "goto":
            return f"go to {self.obj.text}"
        if self.verb == "pickup":
            return f"pick up {self.obj.text}"
        if self.verb == "open":
            return f"open {self.obj.text}"
        if self.verb == "putnext":
            return f"put {self.obj.text} next to {self.near.text}"  # type: ignore[union-attr]
        if self.verb == "drop":
            return f"drop {self.obj.text}"
        return "get to the goal square"


_DESC = r"(?:the|a|an)\s+(?:(red|green|blue|purple|yellow|grey)\s+)?(key|ball|box|door|object)" \
        r"(?:\s+(?:on your left|on your right|in front of you|behind you))?"
_INSTR = [
    (re.compile(rf"^go to {_DESC}$"), "goto"),
    (re.compile(rf"^(?:pick up|get|go get|fetch|you must fetch) {_DESC}$"), "pickup"),
    (re.compile(rf"^open {_DESC}$"), "open"),
]
_PUT = re.compile(rf"^put {_DESC} next to {_DESC}$")
GOAL = Desc("goal")


def _desc(colour: str | None, kind: str) -> Desc:
    return Desc(None if kind == "object" else kind, colour)


@functools.lru_cache(maxsize=4096)
def parse_mission(mission: str) -> tuple[Instr, ...]:
    """The mission's instructions in the order they must be done; () when the planner does not know
    the mission (it then explores)."""
    text = " ".join(mission.lower().strip().rstrip(".").split())
    if "goal" in text and ("get to" in text or "reach" in text or "go to" in text):
        if "key" in text and "door" in text:  # DoorKey: "use the key to open the door and then get to the goal"
            return Instr("open", Desc("door")), Instr("enter", GOAL)
        return (Instr("enter", GOAL),)  # Empty, FourRooms, LavaGap, MultiRoom, ...
    if " after you " in text:
        first, second = text.split(" after you ", 1)
        return parse_mission(second) + parse_mission(first)
    for joint in (", then ", " and "):
        if joint in text:
            a, b = text.split(joint, 1)
            return parse_mission(a) + parse_mission(b)
    if m := _PUT.match(text):
        return (Instr("putnext", _desc(m.group(1), m.group(2)), _desc(m.group(3), m.group(4))),)
    for pattern, verb in _INSTR:
        if m := pattern.match(text):
            return (Instr(verb, _desc(m.group(1), m.group(2))),)
    return ()
