"""The planner of the BabyAI and MiniGrid oracle (`illm_tools.oracles.babyai`): it reads the text an
LLM is given about a BabyAI or MiniGrid state and answers as a player who knows the game would.

It reads the rendered prompt alone, never the environment: the game and mission on the prompt's
first line ("You are an expert player playing BabyAI. The goal is: open the red door."), the B.1
history ("Observation i: ...", "Action i: ...", oldest first; the last observation is the current
one) and the valid actions ("Valid actions: turn left, ..."). Observations are BabyAI-Text as
`illm_tools.envs.babyai` writes it ("You see a red ball 1 step left and 2 steps forward", "You see
a locked yellow door 3 steps forward", "You see a wall 2 steps right", "You carry a blue key").

What it knows about the game:
- Geometry: the agent stands at (0, 0) facing forward (+y); x counts columns to the right. The
  view covers x in [-3, 3] and y in [0, 6]. Keys, balls and boxes block a cell, a closed or locked
  door blocks it until toggled open (a locked one only with a key of its colour), lava kills, open
  doors, goal squares and floor can be entered. The text names a wall only where a ray from the
  agent (forward, left, right) meets one first; BabyAI rooms are rectangles, so a wall seen forward
  at distance d is read as the whole row y = d (the columns x = -d / +d for left and right), unless
  something is seen beyond it. Cells nobody described are empty or unseen; both count as free.
- Missions: BabyAI's grammar (go to / pick up / open / put X next to Y, joined by "and", ", then",
  "after you") and MiniGrid's common ones (get to the goal square, avoid the lava, traverse the
  rooms, use the key to open the door and then get to the goal, fetch/get/go get an object).
  "on your left" and the like refer to the agent's position when the episode began, which the text
  does not give: they are ignored, and any object of that colour and type is a target.
- Which part of a compound mission is current: what the text shows decides (an open target door
  means "open" is done, carrying the object to put next to another means it was picked up); else the
  first part.
- Costs: for the current step (face an object, pick it up, open a door, drop next to another,
  enter a cell) a breadth-first search over (cell, heading) in the view gives every action's
  remaining cost: 1 + the steps left after it; the step's last action ("pick up", "toggle",
  "drop") costs 1 when the agent faces the right cell. An action that changes nothing costs one
  step more than the best; one that undoes progress (picking up or dropping the wrong thing)
  two more; "sleep", "do nothing" and "think" are never useful (two more). Turning and going
  forward tie toward forward, as the BabyAI bot's search prefers going straight.
- Exploration, when no target is in view: the history says where a target seen before has gone
  (turns rotate the view, a forward step shifts it) and the agent turns or walks toward it;
  otherwise it turns toward the side with more room (the BabyAI bot's rule, ties to the right);
  a door that is not the target is a way on (face it, open it, go through) once the agent has
  looked around (its last two actions were turns the same way), and an open space ahead is the
  second choice.

What it cannot know, and the BabyAI bot can: the bot remembers every cell it has seen in the
episode and reads the true grid (walls behind the agent, objects out of view). At history 0 the
planner sees the 7x7 view only, so when the target has left the view it guesses which way to turn.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

from illm_tools.oracles.babyai_map import _STEP, HALF_VIEW, MOVES, UNREACHABLE, Map, _path, _successor
from illm_tools.oracles.babyai_reading import (COLOURS, Desc, Instr, Thing, View, parse_mission,  # noqa: F401
                                               parse_view)
from illm_tools.oracles.base import Scene

PLANNER_VERSION = 1
"""Version of the rules: part of the oracle's fingerprint, so of every cache key of its answers.
CHANGING ANY ANSWER THE PLANNER GIVES MUST BUMP IT."""

GAMES = ("BabyAI", "MiniGrid")
"""The games whose text the planner reads (the prompt's "playing X")."""
CARRIABLE = ("key", "ball", "box")
IRRELEVANT = ("sleep", "do nothing", "think")
TIE = 0.1
"""Extra cost of a turn that ties with going forward (the BabyAI bot prefers going straight)."""


# --- plans -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Answer:
    """The planner's reading of a state: each valid action's cost (lower is better), the current
    step in words, the next steps of the plan, and what the agent is after."""

    costs: dict[str, float]
    goal: str
    """The current step and those after it ("pick up the yellow key, open the yellow door")."""
    plan: tuple[str, ...]
    """The actions the planner would take next (at most 7)."""
    targets: tuple[Thing, ...]
    """The objects in view the current step is about."""
    explore: bool
    """No target in view: the costs are an exploration move's."""
    blocked: bool = False
    """The cell ahead cannot be entered."""


ACTIONS = MOVES + ("pick up", "drop", "toggle") + IRRELEVANT
"""Every action name the planner knows (BabyAI's largest action space, paper Table 5)."""


class Planner:
    """Reads scenes and answers (`answer`); stateless, memoised per distinct state."""

    def __init__(self) -> None:
        self._state = functools.lru_cache(maxsize=65536)(self._answer)

    def answer(self, scene: Scene) -> Answer:
        """The reading of the scene's state, its costs restricted to the scene's valid actions (an
        action the planner does not know costs as much as a useless one)."""
        full = self._state(Scene(scene.game, scene.mission, scene.history, scene.observation, ()))
        if not scene.actions:
            return full
        useless = min(full.costs.values()) + 2
        return Answer({a: full.costs.get(a, useless) for a in scene.actions}, full.goal, full.plan, full.targets,
                      full.explore, full.blocked)

    def _answer(self, scene: Scene) -> Answer:
        view = parse_view(scene.observation)
        grid = Map(view)
        instrs = parse_mission(scene.mission)
        actions = ACTIONS
        instr, rest = _current(instrs, view)
        step = self._step(instr, view, grid, scene) if instr is not None else None
        if step is None:
            costs, plan, explore = self._explore(view, grid, scene, instr)
            targets: tuple[Thing, ...] = ()
        else:
            costs, plan, targets = step
            explore = False
        costs = self._complete(costs, view, grid, actions, instr)
        steps = [i.text for i in rest]
        if instr is not None:  # the step at hand ("pick up the key"), the instruction it serves, the rest
            now = self._step_text(instr, view)
            steps = [now] + ([instr.text] if now != instr.text else []) + steps
        goal = ", ".join(steps or ["explore the room"])
        return Answer({a: costs[a] for a in actions}, goal, tuple(plan), targets, explore, not grid.free(0, 1))

    # the current instruction's step -------------------------------------------------------------
    def _step_text(self, instr: Instr, view: View) -> str:
        sub = _substep(instr, view)
        return sub.text if sub is not None else instr.text

    def _step(self, instr: Instr, view: View, grid: Map, scene: Scene):
        """(costs, plan, targets) for the instruction's next step, or None when its target is not in view."""
        sub = _substep(instr, view)
        if sub is None:
            return None
        targets = tuple(t for t in view.things if sub.obj.matches(t.kind, t.colour)
                        and not (sub.verb == "open" and t.state == "open"))
        if sub.verb == "drop":  # face a free, empty cell next to the agent and drop
            cells = [(x, y) for x, y in ((0, 1), (-1, 0), (1, 0)) if grid.free(x, y) and view.at(x, y) is None]
            goals, finish, targets = grid.facing(cells), "drop", ()
            if not goals:
                return None
        elif sub.verb == "putnext":
            near = tuple(t for t in view.things if sub.near is not None and sub.near.matches(t.kind, t.colour))
            cells = [(t.x + dx, t.y + dy) for t in near for dx, dy in _STEP
                     if grid.free(t.x + dx, t.y + dy) and view.at(t.x + dx, t.y + dy) is None
                     and (t.x + dx, t.y + dy) != (0, 0)]
            goals, finish, targets = grid.facing(cells), "drop", near
        elif sub.verb == "enter":
            goals, finish = {(t.x, t.y, h) for t in targets for h in range(4)}, None
        else:
            goals = grid.facing([(t.x, t.y) for t in targets])
            finish = {"goto": None, "pickup": "pick up", "open": "toggle"}[sub.verb]
        if (not targets and sub.verb != "drop") or not goals:
            return None
        dist = grid.distances(goals)
        if (0, 0, 0) not in dist:  # walled off in this view: let objects be walked through, as if moved
            dist = Map(View((), view.walls, view.carrying)).distances(goals)
        here = dist.get((0, 0, 0), UNREACHABLE)
        last = 0 if finish is None else 1  # the finishing action still to come after the moves
        costs = {a: 1 + dist.get(_successor((0, 0, 0), a, grid), UNREACHABLE) + last + (TIE if a != "go forward" else 0)
                 for a in MOVES}
        plan = _path(dist, grid)
        if finish is not None:
            costs[finish] = 1.0 if here == 0 else here + 2  # the finishing action, or a wasted step
            if here == 0:
                plan = [finish]
            elif len(plan) < 7:
                plan.append(finish)
        return costs, plan, targets

    # no target in view --------------------------------------------------------------------------
    def _explore(self, view: View, grid: Map, scene: Scene, instr: Instr | None):
        """(costs, plan, explore=True): where a target seen before has gone, else look around; a door
        is a way on once the agent has looked around, or at once when the goal square is the target
        (it lies in another room: MultiRoom, DoorKey)."""
        remembered = _remembered(scene)
        fwd_free = grid.free(0, 1)
        if remembered is not None:
            x, y = remembered
            if y > 0 and fwd_free and abs(x) <= y:
                best = "go forward"
            elif x == 0 and y <= 0:  # behind: turn toward the side with more room (the bot's rule)
                best = "turn left" if (view.walls[1] or 9) > (view.walls[2] or 9) else "turn right"
            else:
                best = "turn right" if x > 0 else "turn left"
            costs = {a: 1.0 if a == best else 1.5 for a in MOVES}
            return costs, [best], True
        left, right = (view.walls[1] or HALF_VIEW + 1), (view.walls[2] or HALF_VIEW + 1)
        turn = "turn left" if left > right else "turn right"
        other = "turn right" if turn == "turn left" else "turn left"
        looked = _looked_around(scene)
        door = self._door_step(view, grid)
        if door is not None:
            return door
        open_ahead = fwd_free and (view.walls[0] is None or view.walls[0] >= 3)
        far = fwd_free and view.walls[0] is None
        costs = {turn: 1.0, other: 1.5, "go forward": 0.9 if far else 1.25 if open_ahead and looked else 1.5 if open_ahead else 2.0}
        return costs, [turn, turn] if not looked else [turn], True

    def _door_step(self, view: View, grid: Map):
        doors = [t for t in view.things if t.kind == "door" and
                 (t.state != "locked" or (view.carrying is not None and view.carrying == (t.colour, "key")))]
        if not doors:
            return None
        closed = [t for t in doors if t.state != "open"]
        opened = [t for t in doors if t.state == "open"]
        goals = grid.facing([(t.x, t.y) for t in closed]) | {(t.x, t.y, h) for t in opened for h in range(4)}
        dist = grid.distances(goals)
        if (0, 0, 0) not in dist:
            return None
        facing_closed = dist[(0, 0, 0)] == 0 and view.at(0, 1) in closed
        costs = {a: 1 + dist.get(_successor((0, 0, 0), a, grid), UNREACHABLE) + facing_closed
                 + (TIE if a != "go forward" else 0) for a in MOVES}
        if facing_closed:
            costs["toggle"] = 1.0
            return costs, ["toggle", "go forward"], True
        return costs, _path(dist, grid), True

    # actions other than moves -------------------------------------------------------------------
    def _complete(self, costs: dict, view: View, grid: Map, actions: Sequence[str], instr: Instr | None) -> dict:
        """Every valid action's cost: moves and finishing actions as planned; the rest by what they do."""
        best = min(costs.values()) if costs else 1.0
        front = view.at(0, 1)
        out = {}
        for a in actions:
            if a in costs:
                out[a] = min(costs[a], UNREACHABLE)
            elif a in MOVES:  # a move the plan has no cost for: turning in place
                out[a] = best + 1
            elif a in IRRELEVANT:
                out[a] = best + 2
            elif a == "pick up":
                picks = front is not None and front.kind in CARRIABLE and view.carrying is None
                out[a] = best + 2 if picks else best + 1  # picking up the wrong thing, or nothing happens
            elif a == "drop":
                drops = view.carrying is not None and grid.free(0, 1) and front is None
                out[a] = best + 2 if drops else best + 1
            elif a == "toggle":
                changes = front is not None and front.kind in ("door", "box")
                out[a] = best + 1 if not changes or front.kind == "door" else best + 2
            else:
                out[a] = best + 2
        return out


def _current(instrs: Sequence[Instr], view: View) -> tuple[Instr | None, list[Instr]]:
    """The instruction to work on now and those after it: the first one the view does not show done."""
    for i, instr in enumerate(instrs):
        done = False
        if instr.verb == "open":  # a target door seen open is done (and no door of it closed)
            doors = [t for t in view.things if t.kind == "door" and instr.obj.matches("door", t.colour)]
            done = bool(doors) and all(t.state == "open" for t in doors)
        if not done:
            return instr, list(instrs[i + 1:])
    return None, []


def _substep(instr: Instr, view: View) -> Instr | None:
    """What to do now for an instruction, given what the text shows: a locked target door needs the
    key of its colour first (keys are for doors: with the door out of view, a key of the mission's
    colour in view is fetched), the object to put next to another is picked up first, and something
    already carried is dropped before a key or object can be picked up."""
    carrying = view.carrying
    need: Instr | None = None
    if instr.verb == "open":
        doors = [t for t in view.things if t.kind == "door" and instr.obj.matches("door", t.colour)
                 and t.state != "open"]
        locked = {t.colour for t in doors if t.state == "locked"}
        if doors and not locked:
            return instr  # a closed door: toggle it
        colours = locked or ({instr.obj.colour} if instr.obj.colour else set(COLOURS))
        if carrying is not None and carrying[1] == "key" and carrying[0] in colours:
            return instr  # go and open it (or look for it)
        keys = [t for t in view.things if t.kind == "key" and t.colour in colours]
        if not locked and not keys:
            return instr  # nothing says a key is needed: look for the door
        need = Instr("pickup", Desc("key", next(iter(colours)) if len(colours) == 1 else None))
    elif instr.verb == "putnext":
        if carrying is not None and instr.obj.matches(carrying[1], carrying[0]):
            return instr
        need = Instr("pickup", instr.obj)
    elif instr.verb == "pickup":
        need = instr
    else:
        return instr
    if carrying is not None:
        return Instr("drop", Desc(carrying[1], carrying[0]))
    return need


def _remembered(scene: Scene) -> tuple[int, int] | None:
    """Where the newest target seen in the history lies now (the actions since moved it), or None."""
    instr, _ = _current(parse_mission(scene.mission), parse_view(scene.observation))
    if instr is None or not scene.history:
        return None
    sub = _substep(instr, parse_view(scene.observation))
    desc = (sub or instr).obj
    for k in range(len(scene.history) - 1, -1, -1):
        view = parse_view(scene.history[k][0])
        seen = [t for t in view.things if desc.matches(t.kind, t.colour)]
        if not seen:
            continue
        t = min(seen, key=lambda t: abs(t.x) + t.y)
        x, y = t.x, t.y
        for j in range(k, len(scene.history)):
            before, action = parse_view(scene.history[j][0]), scene.history[j][1]
            if action == "turn left":
                x, y = y, -x
            elif action == "turn right":
                x, y = -y, x
            elif action == "go forward" and Map(before).free(0, 1):
                y -= 1
        return x, y
    return None


def _looked_around(scene: Scene) -> bool:
    """The last two actions were turns the same way (the agent has looked around)."""
    acts = [a for _, a in scene.history[-2:]]
    return len(acts) == 2 and acts[0] == acts[1] and acts[0] in ("turn left", "turn right")


# --- words -------------------------------------------------------------------------------------------
def where(t: Thing) -> str:
    """A coarse place: "adjacent in front", "near, ahead on the left", "far to the right"."""
    d = abs(t.x) + t.y
    dist = "adjacent" if d == 1 else "near" if d <= 3 else "far"
    side = "" if t.x == 0 else " on the left" if t.x < 0 else " on the right"
    if t.y == 0:
        return f"{dist} to the {'left' if t.x < 0 else 'right'}"
    return f"{dist}, ahead{side}" if d != 1 else "adjacent in front"


_PAST = {"turn left": "turned left", "turn right": "turned right", "go forward": "went forward",
         "pick up": "picked something up", "drop": "dropped something", "toggle": "toggled",
         "sleep": "slept", "do nothing": "did nothing", "think": "thought"}


def summary_text(scene: Scene, answer: Answer) -> str:
    """A short deterministic account of the history, one fact a sentence: the step at hand, what
    the agent did, where the step's objects are, what it carries, whether its way ahead is blocked."""
    view = parse_view(scene.observation)
    parts = [f"The agent must {answer.goal.split(', ')[0]}."]
    done = [_PAST.get(a, a) for _, a in scene.history if a]
    if done:
        parts.append(f"It {', then '.join(_runs(done))}.")
    if answer.targets:
        named = sorted({t.name for t in answer.targets})
        places = sorted({where(t) for t in answer.targets})
        parts.append(f"The {' and the '.join(named)} {'is' if len(answer.targets) == 1 else 'are'} {' and '.join(places)}.")
    else:
        parts.append("Nothing it needs is in view.")
    parts.append(f"It carries a {' '.join(view.carrying)}." if view.carrying else "It carries nothing.")
    if answer.blocked and not any(t.x == 0 and t.y == 1 for t in answer.targets):
        parts.append("Its way ahead is blocked.")
    return " ".join(parts)


def _runs(words: list[str]) -> list[str]:
    """["went forward", "went forward", "turned left"] -> ["went forward twice", "turned left"]."""
    out: list[str] = []
    count = 0
    for i, w in enumerate(words):
        count += 1
        if i + 1 == len(words) or words[i + 1] != w:
            out.append(w if count == 1 else f"{w} twice" if count == 2 else f"{w} {count} times")
            count = 0
    return out
