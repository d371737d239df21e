"""The planner of the Crafter oracle (`illm_tools.oracles.crafter`): it reads the text an LLM is given
about a Crafter state (`crafter_reading`) and answers as a player who knows the game would, walking
the view with `crafter_paths`.

What it does, first that applies:
- asleep: sleep on (crafter overrides any action while energy is below its maximum);
- a zombie or skeleton 1 step away: face it and strike;
- a skeleton within 4 steps at health 5 or less: get away (its arrows fly 4 steps; a zombie follows,
  so it is fought);
- vitals: sleep when energy is 1 or less (no zombie in view); drink when drink is 3 or less and water
  is in view, eat (a cow, a ripe plant) when food is; top up when it is cheap (water next to the
  agent or 2 steps away, water in view at drink 6 or less, a cow in view at food 6 or less, a
  cow next to it, a ripe plant); sleep at energy 3 or less and health 7 or more (a zombie strikes a sleeper
  for 7); look for water or food when drink or food is 3 or less;
- the achievement tree, crafter's recipes (`PLACE`, `MAKE`): with a table in the 3x3 cells around the
  agent (crafter's "nearby"; the text tells it: a table 1 step away, or 2 steps on a diagonal) make
  the best tool the inventory allows (wood pickaxe, stone pickaxe, iron pickaxe with a furnace
  nearby too, then the swords) and place a furnace once there is the stone for it; without one, walk
  to a table in view or place one (it keeps the wood for it: a table left behind is out of mind
  when out of view); collect wood up to a stock for the stage (8 before the first pickaxe, 4 after),
  stone (with a wood pickaxe) up to what the furnace, stone sword and one placed stone need, coal,
  iron (with a stone pickaxe), diamonds (with an iron one); place a sapling on faced grass, gather
  one from grass at the very start; place spare stone on faced water, lava or ground;
- else explore for what is missing (trees, water, a cow, stone and what lies in it): a heading
  kept while the inventory and a coarse sum of the vitals stay the same (a hash of them; with a
  history, the last move kept), turned along the edge of the world when it comes within 3 steps,
  digging through trees and stone when it has the pickaxe.

Costs: the steps left to finish the step at hand after each action (the walk's steps, then the
finishing action); an action that changes nothing costs a step more than the best, one that spends
something or puts the agent to sleep two more, a move into a cell that may be lava the most.

What it cannot know from the text: where it has been (a table or water left out of view is gone
for it, so it carries wood for a new table, and thirst sends it exploring), what is behind the
nearest thing of each kind (the text names one instance a kind: a second tree, stone or water cell
next to the agent is unseen, so a move may fail and, memoryless, it may walk back and forth in a
corner until the vitals change the tie order; a second lava cell next to it is unseen too, so a cell
that may be lava costs a lot), which way it faces when it faces ground, whether it is night (zombies
come in numbers; it cannot shelter for the night), and which achievements it has unlocked. The edge
of the world it knows from renderer version 2 on (crafter-text@2 names it in "You see"): without
it, the agent walked into the border and stayed there.
"""
from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass

from illm_tools.oracles.base import Scene
from illm_tools.oracles.crafter_paths import DIRS, GRID, GRID_CELLS, MOVES, UNREACHABLE, Goal, Walk
from illm_tools.oracles.crafter_reading import ACTIONS, GROUND, STEPS, Seen, View, parse_view

PLANNER_VERSION = 1
"""Version of the rules: CHANGING ANY ANSWER THE PLANNER GIVES MUST BUMP IT."""

PLACE = {"stone": ({"stone": 1}, ("grass", "sand", "path", "water", "lava")), "table": ({"wood": 2}, GROUND),
         "furnace": ({"stone": 4}, GROUND), "plant": ({"sapling": 1}, ("grass",))}
"""crafter's data.yaml `place`: what placing each uses, and what the faced cell must be."""
MAKE = {"wood pickaxe": ({"wood": 1}, ("table",)), "stone pickaxe": ({"wood": 1, "stone": 1}, ("table",)),
        "iron pickaxe": ({"wood": 1, "coal": 1, "iron": 1}, ("table", "furnace")),
        "wood sword": ({"wood": 1}, ("table",)), "stone sword": ({"wood": 1, "stone": 1}, ("table",)),
        "iron sword": ({"wood": 1, "coal": 1, "iron": 1}, ("table", "furnace"))}
"""crafter's data.yaml `make`: what making each uses, and what must be nearby."""
TOOLS = ("wood pickaxe", "stone pickaxe", "iron pickaxe", "wood sword", "stone sword", "iron sword")
"""What to make, in order of use (pickaxes open the next materials, swords shorten fights)."""
WOOD_STOCK = {None: 8, "wood pickaxe": 4, "stone pickaxe": 4, "iron pickaxe": 2}
"""Wood gathered while trees are in view, by the best pickaxe held: a table (2), the tools of the stage."""
CLOCKWISE = (2, 1, 3, 0)
"""North, east, south, west, as indices into `MOVES`."""
TIE = 0.05
"""What breaks a tie between two moves (far below a step)."""
STRIKES = {"zombie": "fight the zombie", "skeleton": "fight the skeleton", "cow": "eat the cow",
           "ripe plant": "eat the plant", "water": "drink water", "tree": "collect wood", "stone": "collect stone",
           "coal": "collect coal", "iron": "collect iron", "diamond": "collect a diamond"}


@dataclass(frozen=True)
class Step:
    """The step at hand: its words, what it acts on (`kinds`, for a walk to face one), how it finishes."""

    text: str
    finish: str = "interact"
    kinds: tuple[str, ...] = ()
    near: tuple[str, ...] = ()
    """Walk until these are nearby, then finish (make a tool)."""
    heading: int | None = None
    """Explore: walk this way (an index into `MOVES`)."""


@dataclass(frozen=True)
class Answer:
    costs: dict[str, float]
    step: Step
    goal: str
    plan: tuple[str, ...]


def make_text(tool: str) -> str:
    return f"make {'an' if tool[0] in 'aeiou' else 'a'} {tool}"


def best_pickaxe(view: View) -> str | None:
    return next((t for t in ("iron pickaxe", "stone pickaxe", "wood pickaxe") if view.has(t)), None)


def can_make(view: View, tool: str) -> bool:
    uses, nearby = MAKE[tool]
    return all(view.has(k, n) for k, n in uses.items()) and all(view.near(k) for k in nearby)


def can_place(view: View, thing: str) -> bool:
    uses, where = PLACE[thing]
    return all(view.has(k, n) for k, n in uses.items()) and view.facing in where


class Planner:
    """Reads scenes and answers (`answer`); memoised per distinct state."""

    def __init__(self) -> None:
        self._state = functools.lru_cache(maxsize=65536)(self._answer)

    def answer(self, scene: Scene) -> Answer:
        last = next((a for _, a in reversed(scene.history) if a), "") if scene.history else ""
        full = self._state(scene.observation, last if last in STEPS else "")
        if not scene.actions:
            return full
        worst = min(full.costs.values()) + 2
        return Answer({a: full.costs.get(a, worst) for a in scene.actions}, full.step, full.goal, full.plan)

    def _answer(self, observation: str, last_move: str) -> Answer:
        view = parse_view(observation)
        step = choose(view, last_move)
        costs, plan = self._costs(view, step)
        return Answer(costs, step, ", ".join(goal_steps(view, step)), tuple(plan))

    def _costs(self, view: View, step: Step) -> tuple[dict[str, float], list[str]]:
        costs: dict[str, float] = {}
        plan: list[str] = []
        immediate = step.finish == "sleep" or (step.finish.startswith("make ") and not step.near)
        if immediate or (step.finish == "interact" and not step.kinds):  # sleep, make, gather a sapling
            costs[step.finish] = 1.0
            plan = [step.finish]
        elif step.finish.startswith("place "):
            costs, plan = _placing(view, step.finish)
        else:
            walk = Walk(view, _goal(view, step))
            costs = _ties(walk.first(), _toward(view, step), view)
            plan = walk.path(min(costs, key=costs.get) if costs else None)
            if step.near:
                finish = 1.0 if all(view.near(k) for k in step.near) else None
                if finish:
                    costs, plan = {step.finish: 1.0}, [step.finish]
                else:
                    costs = {a: c + 1 for a, c in costs.items() if a != "interact" or c < UNREACHABLE}
                    plan = (plan + [step.finish])[:7]
            elif plan and len(plan) < 7 and step.heading is None and plan[-1] != "interact":
                plan.append("interact")
        return _complete(view, step, costs), plan


def _goal(view: View, step: Step) -> Goal:
    if step.heading is not None:
        dx, dy = DIRS[step.heading]
        far = frozenset(c for c in GRID_CELLS if (dx and c[0] * dx == GRID[0]) or (dy and c[1] * dy == GRID[1]))
        return Goal(reach=far)
    if step.near:
        around = None
        for kind in step.near:
            cells = {(x + i, y + j) for x, y in view.seen[kind].cells for i in (-1, 0, 1) for j in (-1, 0, 1)}
            around = cells if around is None else around & cells
        return Goal(reach=frozenset(around or ()) - {(0, 0)})
    cells = frozenset(c for k in step.kinds if k in view.seen for c in view.seen[k].cells)
    return Goal(face=cells, through=not set(step.kinds) & {"zombie", "skeleton", "cow"})


def _toward(view: View, step: Step) -> tuple[float, float]:
    """Which way the step leads: the heading, or the nearest target's first candidate cell."""
    if step.heading is not None:
        return DIRS[step.heading]
    for kind in step.kinds + step.near:
        if kind in view.seen:
            cells = view.seen[kind].cells
            return (sum(x for x, _ in cells) / len(cells), sum(y for _, y in cells) / len(cells))
    return (0.0, 0.0)


def _ties(costs: dict[str, float], toward: tuple[float, float], view: View) -> dict[str, float]:
    """Break ties between moves: the one most along `toward` first, then an order drawn from the
    inventory and vitals (one way round an obstacle for a while, the other way later: without a
    memory, a fixed order walks the agent back and forth in a corner the text does not show);
    each next one TIE more. Interact (a dig, a strike) goes before them all."""
    salt = zlib.crc32(repr((sorted(view.items.items()), sorted(view.vitals.items()))).encode())
    shuffled = sorted(MOVES, key=lambda m: zlib.crc32(m.encode(), salt))
    order = sorted(MOVES, key=lambda m: (-(STEPS[m][0] * toward[0] + STEPS[m][1] * toward[1]), shuffled.index(m)))
    return {a: c + (TIE * (1 + order.index(a)) if a in MOVES and c < UNREACHABLE else 0.0) for a, c in costs.items()}


def _placing(view: View, action: str) -> tuple[dict[str, float], list[str]]:
    """Placing needs the faced cell to be of the right ground: at once, or after a move that ends facing
    ground (a step onto free ground faces the cell beyond it)."""
    if can_place(view, action.split(" ", 1)[1]):
        return {action: 1.0}, [action]
    costs = {}
    for move, (dx, dy) in STEPS.items():
        kind, maybe = view.kinds.get((dx, dy), (None, frozenset()))
        beyond = view.kinds.get((2 * dx, 2 * dy), (None, frozenset("?")))
        if "lava" in maybe:
            costs[move] = UNREACHABLE
        elif kind is not None:
            costs[move] = 3.0
        else:
            costs[move] = 2.0 if not beyond[1] else 2.5
    best = min(costs, key=costs.get)
    return costs, [best, action]


def _complete(view: View, step: Step, costs: dict[str, float]) -> dict[str, float]:
    """Every action's cost: those the step planned, the rest by what they do."""
    best = min(costs.values()) if costs else 1.0
    out = {}
    for action in ACTIONS:
        if action in costs:
            out[action] = min(costs[action], UNREACHABLE)
        elif action == "sleep":
            out[action] = best + (1 if view.vitals["energy"] >= 9 else 2)
        elif action.startswith("make "):
            out[action] = best + (2 if can_make(view, action[5:]) else 1)
        elif action.startswith("place "):
            out[action] = best + (2 if can_place(view, action[6:]) else 1)
        else:
            out[action] = best + 1
    return out


# --- the step at hand --------------------------------------------------------------------------------
def choose(view: View, last_move: str = "") -> Step:
    """The step at hand (see the module docstring for the order)."""
    seen, vit = view.seen, view.vitals

    def within(kind: str, dist: int) -> bool:
        return kind in seen and seen[kind].dist <= dist

    if view.sleeping:
        return Step("sleep", finish="sleep")
    for foe in ("zombie", "skeleton"):
        if within(foe, 1):
            return Step(STRIKES[foe], kinds=(foe,))
    if within("skeleton", 4) and vit["health"] <= 5:
        return Step("get away from the skeleton", finish="", heading=_away(seen["skeleton"]))
    if vit["energy"] <= 1 and "zombie" not in seen:
        return Step("sleep", finish="sleep")
    urgent = sorted((vit[v], v) for v in ("drink", "food") if vit[v] <= 3)
    for _, vital in urgent:
        kinds = ("water",) if vital == "drink" else ("cow", "ripe plant")
        if any(k in seen for k in kinds):
            return Step(STRIKES[next(k for k in kinds if k in seen)], kinds=kinds)
    if (vit["drink"] < 9 and within("water", 2)) or (vit["drink"] <= 6 and "water" in seen):
        return Step("drink water", kinds=("water",))
    if within("cow", 1) and vit["food"] < 9 or (vit["food"] <= 6 and "cow" in seen):
        return Step("eat the cow", kinds=("cow",))
    if "ripe plant" in seen and vit["food"] < 9:
        return Step("eat the plant", kinds=("ripe plant",))
    if vit["energy"] <= 3 and vit["health"] >= 7 and "zombie" not in seen:
        return Step("sleep", finish="sleep")
    if urgent:
        return Step(f"find {_missing(view)}", finish="", heading=_heading(view, last_move))
    work = _work(view)
    if work is not None:
        return work
    return Step(f"find {_missing(view)}", finish="", heading=_heading(view, last_move))


def _work(view: View) -> Step | None:
    """The achievement tree's next step that the view allows, or None (explore)."""
    seen = view.seen
    pickaxe = best_pickaxe(view)
    if view.has("sapling") and view.facing == "grass":
        return Step("place a sapling", finish="place plant")
    for tool in TOOLS:
        if not view.has(tool) and can_make(view, tool) and (tool == "wood pickaxe" or view.has("wood pickaxe")):
            return Step(make_text(tool), finish=f"make {tool}")
    stone = PLACE["furnace"][0]["stone"]
    if view.has("stone pickaxe") and view.near("table") and not view.near("furnace") and view.has("stone", stone):
        return Step("place a furnace", finish="place furnace")
    wanted = [t for t in TOOLS[:3] if not view.has(t) and all(view.has(k, n) for k, n in MAKE[t][0].items())]
    if wanted:
        tool = wanted[0]
        if "furnace" in MAKE[tool][1] and not view.near("furnace"):
            if view.near("table") and view.has("stone", stone):
                return Step("place a furnace", finish="place furnace")
            if "furnace" in seen and "table" in seen:
                return Step(f"go to the table and furnace to {make_text(tool)}", finish=f"make {tool}",
                            near=("table", "furnace"))
        elif "table" in seen and (seen["table"].dist <= 6 or not view.has("wood", 3)):
            return Step(f"go to the table to {make_text(tool)}", finish=f"make {tool}", near=("table",))
        needs_wood = view.has("wood", PLACE["table"][0]["wood"] + MAKE[tool][0]["wood"])
        more_wood = "tree" in seen and not view.has("wood", WOOD_STOCK[pickaxe])
        if needs_wood and not more_wood and "furnace" not in MAKE[tool][1]:
            return Step("place a table", finish="place table")
        if needs_wood and "furnace" in MAKE[tool][1] and view.has("stone", stone) and not view.near("table"):
            return Step("place a table", finish="place table")
    if not view.items and view.facing == "grass" and "plant" not in seen:
        return Step("collect a sapling", finish="interact")
    if "tree" in seen and not view.has("wood", WOOD_STOCK[pickaxe]):
        return Step("collect wood", kinds=("tree",))
    targets = [("diamond", "iron pickaxe", 9), ("iron", "stone pickaxe", 2), ("coal", "wood pickaxe", 2),
               ("stone", "wood pickaxe", stone + 2 if view.has("stone pickaxe") else 1)]
    for kind, tool, enough in targets:
        if kind in seen and view.has(tool) and not view.has(kind, enough):
            return Step(STRIKES[kind], kinds=(kind,))
    if view.has("stone", stone + 3) and view.facing in PLACE["stone"][1]:
        return Step("place stone", finish="place stone")
    return None


def _missing(view: View) -> str:
    """What the exploration is for (words)."""
    vit = view.vitals
    if vit["drink"] <= 3:
        return "water"
    if vit["food"] <= 3:
        return "a cow"
    if not view.has("wood pickaxe"):
        return "trees" if not view.has("wood", 3) else "a place for a table"
    if not view.has("stone pickaxe"):
        return "stone" if not view.has("stone") else "trees"
    if not view.has("iron pickaxe"):
        return "coal and iron"
    return "diamonds"


def _away(seen: Seen) -> int:
    """The move away from a thing (along the axis it is farther on)."""
    x = sum(c[0] for c in seen.cells) / len(seen.cells)
    y = sum(c[1] for c in seen.cells) / len(seen.cells)
    if abs(x) >= abs(y):
        return MOVES.index("move west" if x > 0 else "move east")
    return MOVES.index("move north" if y > 0 else "move south")


def _heading(view: View, last_move: str) -> int:
    """Which way to explore: the last move's (a history tells it), else one drawn from the inventory
    and a coarse sum of the vitals (constant while they are, some 20 to 40 steps: a straight walk, not
    a random one, and another one later); turned a quarter (the same way each time for one inventory)
    while the edge of the world lies within 3 steps that way."""
    vit = view.vitals
    key = repr((sorted(view.items.items()), (vit["food"] + vit["drink"] + vit["energy"]) // 5)).encode()
    heading = MOVES.index(last_move) if last_move else zlib.crc32(key) % 4
    turn = 1 if zlib.crc32(repr(sorted(view.items.items())).encode()) % 2 else -1
    edge = view.seen.get("edge")
    for _ in range(3):
        if edge is None or edge.dist > 3 or edge.where != MOVES[heading].split()[1]:
            break
        heading = CLOCKWISE[(CLOCKWISE.index(heading) + turn) % 4]
    return heading


# --- words -------------------------------------------------------------------------------------------
def goal_steps(view: View, step: Step) -> list[str]:
    """The step at hand and the achievement tree's next two ("collect wood, place a table, make a wood pickaxe")."""
    out = [step.text]
    tree = ["collect wood", "place a table", "make a wood pickaxe", "make a wood sword", "collect stone",
            "make a stone pickaxe", "make a stone sword", "place a furnace", "collect coal", "collect iron",
            "make an iron pickaxe", "make an iron sword", "collect a diamond"]
    done = {"wood pickaxe": 3, "stone pickaxe": 6, "iron pickaxe": 11}
    start = max([done[t] for t in done if view.has(t)] + [0])
    held = {make_text(t) for t in TOOLS if view.has(t)}
    out += [s for s in tree[start:] if s != step.text and s not in held][:2]
    return out
