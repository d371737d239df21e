"""What the MiniHack oracle (`illm_tools.oracles.minihack`) reads in a MiniHack-Text observation, and
the game knowledge it brings: NetHack's keys behind the action names, its monsters' names.

The text is MiniHack-Text version 2 (`illm_tools.envs.minihack_text`, its module docstring is the
grammar): phrases joined by "; ": "message: ...", "you are levitating", "your hit points are low
(3 of 14)", map phrases "<thing> <band> <direction> (<offset>)" ("a ring near northwest (2 west,
4 north)"), "walls adjacent north and west", "you carry ...". This module reads them into a
`View`; it never reads an environment (the oracles sit below `illm_tools.envs`), so the few names it
shares with the renderer are written here again and checked against it by tests/test_oracle_minihack.py.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field

DIRECTIONS: dict[str, tuple[int, int]] = {
    "north": (0, -1), "northeast": (1, -1), "east": (1, 0), "southeast": (1, 1),
    "south": (0, 1), "southwest": (-1, 1), "west": (-1, 0), "northwest": (-1, -1)}
"""The renderer's 8 compass directions -> (dx, dy), screen up is north (dy < 0)."""

KEYS: dict[str, str] = {
    "a": "apply", "b": "move southwest", "c": "close a door", "d": "drop", "e": "eat", "f": "fire",
    "g": "rush", "h": "move west", "i": "show inventory", "j": "move south", "k": "move north",
    "l": "move east", "n": "move southeast", "o": "open a door", "p": "pay", "q": "drink (quaff)",
    "r": "read", "s": "search", "t": "throw", "u": "move northeast", "v": "show short version",
    "w": "wield", "x": "swap weapons", "y": "move northwest", "z": "zap", "P": "put on", "R": "remove an accessory",
    "W": "wear", "T": "take off", "Q": "fill quiver", ",": "pick up", "\x1b": "escape"}
"""NetHack's key (vi-keys, number_pad off, as NLE plays) -> the action name the renderer gives the
action bound to it: how an expert answers a prompt such as "What do you want to put on? [f or ?*]"
when no action is named after letters (MiniHack's LavaCross action sets hold "fire", whose key is f,
for that). Game knowledge, not the env's state."""

_PHRASE = re.compile(r"^(?P<what>.+?) (?P<band>adjacent|very near|near|far|very far) "
                     r"(?P<dir>north|northeast|east|southeast|south|southwest|west|northwest) \((?P<off>[^)]*)\)$")
_PART = re.compile(r"(\d+) (east|west|north|south)")
_COUNT = re.compile(r"^(?:a|an|the|\d+) ")
STAIRS = ("staircase down", "ladder down")
LEVITATION_ITEMS = ("ring", "potion", "pair of boots")


@dataclass(frozen=True)
class Seen:
    """One map phrase: what (singular, no article or count: "boulder", "staircase down", "newt"), its
    nearest square's offset (dx east, dy south) and how many squares the phrase covers."""

    name: str
    dx: int
    dy: int
    count: int = 1

    @property
    def distance(self) -> int:
        """Moves to it, diagonals allowed (Chebyshev)."""
        return max(abs(self.dx), abs(self.dy))


@dataclass
class View:
    """One MiniHack-Text observation, read."""

    message: str = ""
    levitating: bool = False
    no_diagonal: bool = False
    """A doorway forbids a diagonal step: the message said so ("You can't move diagonally out of an
    intact doorway."), or the planner knows the agent stands in one (`minihack._in_doorway`)."""
    seen: list[Seen] = field(default_factory=list)
    walls: set[tuple[int, int]] = field(default_factory=set)
    """Offsets of the neighbouring wall squares."""
    carried: str = ""
    """The "you carry" list as written (empty: nothing beyond the kit)."""

    def of(self, *names: str) -> list[Seen]:
        """The phrases naming any of `names`, nearest first."""
        return sorted((s for s in self.seen if s.name in names), key=lambda s: s.distance)


def _singular(what: str) -> tuple[str, int]:
    """"2 boulders" -> ("boulder", 2); "the staircase down" -> ("staircase down", 1); "lava" -> ("lava", 1)."""
    count = 1
    m = _COUNT.match(what)
    if m:
        head = m.group(0).strip()
        what = what[m.end():]
        if head.isdigit():
            count = int(head)
            what = _unplural(what)
    return what, count


def _unplural(noun: str) -> str:
    """The renderer's plurals undone well enough to compare names ("boulders" -> "boulder",
    "staircases down" -> "staircase down", "pairs of boots" -> "pair of boots")."""
    head, sep, tail = noun.partition(" of ")
    if not sep and noun.endswith((" up", " down")):
        head, tail = noun.rsplit(" ", 1)
        sep = " "
    *words, last = head.split(" ")
    for plural, single in (("ies", "y"), ("ches", "ch"), ("shes", "sh"), ("xes", "x"), ("ses", "s"), ("s", "")):
        if last.endswith(plural):
            last = last[: -len(plural)] + single
            break
    return " ".join((*words, last)) + sep + tail


def read_view(text: str) -> View:
    """The `View` of one observation's text."""
    view = View()
    for phrase in text.split("; "):
        if phrase.startswith("message: "):
            view.message = phrase[len("message: "):]
            view.no_diagonal = "diagonally" in view.message
        elif phrase.startswith("you are "):
            view.levitating = "levitating" in phrase or "flying" in phrase
        elif phrase.startswith("you carry "):
            view.carried = phrase[len("you carry "):]
        elif phrase.startswith(("walls adjacent ", "a wall adjacent ")):
            names = phrase.split(" adjacent ", 1)[1].replace(" and ", ", ").split(", ")
            view.walls = {DIRECTIONS[n] for n in names if n in DIRECTIONS}
        elif m := _PHRASE.match(phrase):
            name, count = _singular(m.group("what"))
            dx = dy = 0
            for n, word in _PART.findall(m.group("off")):
                if word in ("east", "west"):
                    dx = int(n) * (1 if word == "east" else -1)
                else:
                    dy = int(n) * (1 if word == "south" else -1)
            view.seen.append(Seen(name, dx, dy, count))
    return view


@functools.lru_cache(maxsize=1)
def monster_names() -> frozenset[str]:
    """Every NetHack monster species' name (from nle's monster table: game knowledge)."""
    from nle import nethack

    return frozenset(nethack.permonst(i).mname for i in range(nethack.NUMMONS))


def is_hostile_monster(name: str) -> bool:
    """A monster that is not the agent's pet ("tame little dog") and not a remembered unseen one."""
    return name in monster_names()
