"""The MiniHack oracle: a planner that reads MiniHack-Text (version 2, `illm_tools.envs.minihack_text`)
as a player who knows NetHack would, behind the `Oracle` contract.

It reads the prompt alone (`minihack_reading.read_view`: the message, being levitating, the map's
things with the offset of each phrase's nearest square, the neighbouring walls, what is carried) and
the mission. The step at hand, first that applies:

1. Answer a prompt in the message: "What do you want to put on? [f or ?*]" takes the action whose
   key is f ("fire": NetHack's keys, `KEYS`); "Which ring-finger, Right or Left? [rl]" r; a yes/no
   question no; "--More--" the next message.
2. Levitation, when the mission says to float over the lava and the agent is not levitating: a
   carried ring is put on, a potion drunk, boots worn; an item lying here ("You see here a ring")
   picked up; else the nearest ring, potion or pair of boots in view is walked to.
3. A hostile monster adjacent is fought, unless the staircase down is a step away.
4. The staircase down, when in view, is walked to (reaching it ends MiniHack's navigation tasks).
5. Else a way on: the door or doorway in view that leads away from where the agent came from (the
   history's moves, where the prompt has them), else the nearest one; else any free direction.

Costs: each move's is 1 + the moves left to the target after it (Chebyshev distance, diagonals
allowed); a hostile monster adjacent is attacked (moving into it) unless the staircase down is one
step away: fleeing a jackal as fast as the agent only gives it free bites, and the rogue of
MiniHack's navigation tasks beats the newts and jackals of "-Monster" levels; another monster in the
way is attacked rather than side-stepped (half a step better than a step that makes no progress);
a step onto an object costs half a step more (autopickup would burden the agent); a move
into a wall, or diagonally where the message says a doorway forbids it, wastes the
step (one more than staying); a move into lava or water without levitating dies or drowns (twenty
more); running costs one more than the step it starts with; any other action wastes a step (one
more), and the step's own action (pick up, put on, a prompt's key) is 1 + what is left after it.

What it cannot do from the text: cross water (River levels need boulders pushed into the water,
which the greedy walk does not plan: a boulder in the way is pushed only by walking into it), freeze
lava with a wand of cold or a frost horn (LavaCross-Full's other items), or remember rooms it has
left (the text describes what is in view; the history only the last few steps).
"""

from __future__ import annotations

import random
import re
from dataclasses import dataclass

from illm_tools.oracles.base import PlannerOracle, Scene
from illm_tools.oracles.minihack_reading import (DIRECTIONS, KEYS, LEVITATION_ITEMS, STAIRS, Seen,
                                                 View, is_hostile_monster, read_view)

PLANNER_VERSION = 1
"""CHANGING ANY ANSWER THE PLANNER GIVES MUST BUMP IT (the oracle backend's fingerprint names it)."""
DEADLY = 20.0
"""Extra cost of a step into lava or water without levitating: it ends the episode."""
DOORS = ("doorway", "open door", "closed door", "broken door")
_FLOOR_LIKE = (*DOORS, "staircase up", "staircase down", "ladder up", "ladder down", "lava", "water", "ice")
_PROMPT = re.compile(r"\[([A-Za-z])[A-Za-z-]* or \?\*\]")
_CHOICE = re.compile(r"\[([a-z]+)\]")
_USE = (("ring", "put on", "put on the ring"), ("potion", "drink (quaff)", "drink the potion"),
        ("boots", "wear", "wear the boots"))


@dataclass
class Answer:
    """The planner's answer for one state."""

    costs: dict[str, float]
    goal: str
    plan: list[str]
    view: View
    """The observation it answered, read."""
    target: Seen | None = None
    """What it walks to, as the text named it, if anything."""


def _sign(v: int) -> int:
    return (v > 0) - (v < 0)


def _dist(dx: int, dy: int) -> int:
    return max(abs(dx), abs(dy))


def _moved(history: tuple[tuple[str, str], ...]) -> tuple[int, int]:
    """The agent's displacement over the history's moves whose next message did not say it bumped
    into something (an estimate: a monster or boulder in the way also stops a move)."""
    x = y = 0
    for i, (_, action) in enumerate(history):
        if action.startswith("move ") and action[5:] in DIRECTIONS:
            after = history[i + 1][0] if i + 1 < len(history) else ""
            if "It's a wall" in after or "It's solid stone" in after:
                continue
            dx, dy = DIRECTIONS[action[5:]]
            x, y = x + dx, y + dy
    return x, y


class Planner:
    """Answers one scene at a time (see the module docstring); memoised per state."""

    def __init__(self) -> None:
        self._memo: dict[tuple[str, tuple[str, ...]], Answer] = {}

    def answer(self, scene: Scene) -> Answer:
        key = (scene.state_id, scene.actions)
        found = self._memo.get(key)
        if found is None:
            found = self._memo[key] = self._answer(scene)
        return found

    def _answer(self, scene: Scene) -> Answer:
        view = read_view(scene.observation)
        actions = scene.actions
        step = _prompt_answer(view, actions) or self._item_step(scene, view, actions)
        if step is not None:  # one action does the step at hand
            action, goal = step
            return Answer(_costs(actions, view, None, best=action), goal, [action], view)
        target, goal = self._target(scene, view)
        view.no_diagonal = view.no_diagonal or _in_doorway(scene, view)
        return Answer(_costs(actions, view, target), goal, _walk(view, target), view, target)

    @staticmethod
    def _item_step(scene: Scene, view: View, actions: tuple[str, ...]) -> tuple[str, str] | None:
        """Put on, drink or wear a carried levitation item, or pick one up from under the agent."""
        if not _needs_levitation(scene.mission) or view.levitating:
            return None
        for item, verb, goal in _USE:
            if item in view.carried and "(on " not in view.carried and "(being worn)" not in view.carried \
                    and verb in actions:
                return verb, f"{goal}, float over the lava, reach the staircase down"
        here = view.message.lower()
        if ("you see here" in here and any(i in here for i in ("ring", "potion", "boots"))) or "several objects here" in here:
            if "pick up" in actions:
                return "pick up", "pick up the levitation item, use it, float over the lava, reach the staircase down"
        return None

    @staticmethod
    def _target(scene: Scene, view: View):
        """What to walk to, and the goal's words."""
        if _needs_levitation(scene.mission) and not view.levitating:
            items = view.of(*LEVITATION_ITEMS)
            if items:
                return items[0], f"pick up the {items[0].name}, use it, float over the lava, reach the staircase down"
        stairs = view.of(*STAIRS)
        if stairs and stairs[0].distance == 1:
            return stairs[0], "reach the staircase down"
        monsters = [s for s in view.seen if s.distance == 1 and is_hostile_monster(s.name)]
        if monsters:  # it would follow and bite: fight it where it stands
            return monsters[0], f"fight the {monsters[0].name}, reach the staircase down"
        if stairs:
            return stairs[0], "reach the staircase down"
        doors = view.of(*DOORS)
        if doors:
            door = _way_on(doors, view, scene.history)
            return door, f"go through the {door.name}, find the staircase down"
        return None, "explore to find the staircase down"


def _way_on(doors: list, view: View, history) -> object:
    """The door to go through: the nearest closed one (a door the agent opened is open: closed ones
    lead where it has not been); else the nearest one farther from the staircase up (where the
    episode began) than the agent is, when the staircase up is in view; else the nearest one ahead
    of the history's moves; else the nearest one."""
    closed = [d for d in doors if d.name == "closed door"]
    if closed:
        return closed[0]
    up = view.of("staircase up")
    if up:
        ux, uy = up[0].dx, up[0].dy
        away = [d for d in doors if _dist(d.dx - ux, d.dy - uy) > _dist(ux, uy)]
        if away:
            return away[0]
    mx, my = _moved(history)
    ahead = [d for d in doors if d.dx * mx + d.dy * my > 0] if (mx or my) else []
    return (ahead or doors)[0]


def _in_doorway(scene: Scene, view: View) -> bool:
    """Whether the agent stands in a doorway: its last move took it onto the square where the
    observation before showed a door (a move the message, `view`'s, did not say failed)."""
    if not scene.history:
        return False
    before, action = scene.history[-1]
    if not action.startswith("move ") or action[5:] not in DIRECTIONS:
        return False
    d = DIRECTIONS[action[5:]]
    if any(w in view.message for w in ("You can't", "It's a wall", "resists", "locked")):
        return False
    return any((s.dx, s.dy) == d and s.name in DOORS for s in read_view(before).seen)


def _steps_to(target, x: int, y: int) -> int:
    """Moves from (x, y) to the target: Chebyshev, and for a door one more unless it is entered
    straight (NetHack forbids moving diagonally into or out of a doorway): the square before it, on
    the side of its larger offset, is where it is entered from."""
    dx, dy = target.dx - x, target.dy - y
    if target.name not in DOORS or not (dx and dy):
        return _dist(dx, dy)
    ax, ay = (dx - _sign(dx), dy) if abs(dx) >= abs(dy) else (dx, dy - _sign(dy))
    return _dist(ax, ay) + 1


def _needs_levitation(mission: str) -> bool:
    return "levitation" in mission or "float over" in mission


def _prompt_answer(view: View, actions: tuple[str, ...]) -> tuple[str, str] | None:
    """The action that answers a prompt in the message, if any (see the module docstring)."""
    message = view.message
    if "--More--" in message and "next message" in actions:
        return "next message", "read the next message"
    m = _PROMPT.search(message)
    letter = m.group(1) if m else None
    if letter is None and (c := _CHOICE.search(message)):
        letter = "n" if c.group(1).startswith("yn") else c.group(1)[0]
    if letter is None:
        return None
    name = KEYS.get(letter)
    if name in actions:
        return name, f"answer {letter}"
    return ("escape", "escape the prompt") if "escape" in actions else None


def _blocked(view: View, d: tuple[int, int]) -> float:
    """The extra cost of a step in direction d: 0 free, 1 wasted (a wall), DEADLY (lava or water
    without levitating)."""
    if d in view.walls:
        return 1.0
    here = [s for s in view.seen if (s.dx, s.dy) == d]
    if not view.levitating and any(s.name in ("lava", "water") for s in here):
        return DEADLY
    if view.no_diagonal and d[0] and d[1]:
        return 1.0
    return 0.0


def _costs(actions: tuple[str, ...], view: View, target, *, best: str | None = None) -> dict[str, float]:
    """Every valid action's cost (see the module docstring); `best`: the one action that does the step."""
    if best is not None:
        return {a: 1.0 if a == best else 2.0 + (_blocked(view, DIRECTIONS[a[5:]]) if a[5:] in DIRECTIONS else 0.0)
                for a in actions}
    left = _steps_to(target, 0, 0) if target is not None else 8
    out: dict[str, float] = {}
    for a in actions:
        verb, _, where = a.partition(" ")
        if verb in ("move", "run") and where in DIRECTIONS:
            d = DIRECTIONS[where]
            extra = _blocked(view, d)
            there = [s.name for s in view.seen if (s.dx, s.dy) == d]
            if any(is_hostile_monster(n) for n in there):
                after = 0.0 if target is not None and target.name in there else left - 0.5  # an attack
            elif target is None:
                after = left if extra else left - 0.5  # exploring: any free step is as good as another
            elif target.name in DOORS and (d[0], d[1]) == (target.dx, target.dy) and d[0] and d[1]:
                after, extra = left, 1.0  # diagonally into a doorway: refused
            else:
                after = _steps_to(target, *d)
                if there and target.name not in there and not all(n in _FLOOR_LIKE for n in there):
                    after += 0.5  # a step onto an object picks it up (autopickup): a burden at last
            out[a] = (1.0 + left + extra) if extra else 1.0 + after
            out[a] += 1.0 if verb == "run" else 0.0
        else:
            out[a] = 2.0 + left
    return out


def _walk(view: View, target, steps: int = 5) -> list[str]:
    """The next few moves straight toward the target (the plan's words)."""
    if target is None:
        return ["look around"]
    names = {v: k for k, v in DIRECTIONS.items()}
    dx, dy, plan = target.dx, target.dy, []
    while (dx or dy) and len(plan) < steps:
        d = (_sign(dx), _sign(dy))
        plan.append(f"move {names[d]}")
        dx, dy = dx - d[0], dy - d[1]
    return plan or ["wait"]


def summary_text(scene: Scene, answer: Answer) -> str:
    """One fact a sentence: the step at hand, where its target is, being levitating, what is carried."""
    view = answer.view  # the target's nearest phrase of its name (a door chosen farther is named by the nearest)
    target = next((s for s in view.seen if answer.target is not None and s.name == answer.target.name), None)
    parts = [f"The agent must {answer.goal.split(', ')[0]}."]
    if target is not None:
        parts.append(f"The {target.name} is {_dist(target.dx, target.dy)} steps away.")
    else:
        parts.append("Nothing it needs is in view.")
    if view.levitating:
        parts.append("It is levitating.")
    parts.append(f"It carries {view.carried}." if view.carried else "It carries nothing.")
    return " ".join(parts)


class MiniHackOracle(PlannerOracle):
    """MiniHack's oracle (see the module docstring)."""

    families = ("MiniHack",)
    version = f"minihack-planner@{PLANNER_VERSION}"
    planner_class = Planner

    def summary(self, scene: Scene, answer: Answer) -> str:
        return summary_text(scene, answer)

    def random_text(self, scene: Scene, task: str, rng: random.Random) -> str:
        things = ("staircase down", "ring", "potion", "boulder", "door", "newt", "lava", "water")
        moves = tuple(f"move {d}" for d in DIRECTIONS)
        if task == "goal":
            return f"reach the {rng.choice(things)}"
        if task == "plan":
            return ", ".join(rng.choice(moves) for _ in range(rng.randint(1, 5)))
        return (f"The agent must reach the {rng.choice(things)}. The {rng.choice(things)} is "
                f"{rng.randint(1, 12)} steps away. It carries nothing.")
