"""How the Crafter oracle's planner walks the view (`illm_tools.oracles.crafter_planner`): a shortest
path search over (cell, heading) around the agent, with crafter's rules of movement.

crafter's rules it follows (crafter/objects.py): a move turns the agent to face its direction and
steps there when the cell is grass, sand or path with no creature or object on it; otherwise the
agent only turns, so moving toward something that blocks is how the agent comes to face it. "interact"
acts on the faced cell: it collects a tree (which leaves grass), stone and coal with a wood pickaxe,
iron with a stone one, a diamond with an iron one (each leaves a path), so the planner may dig its way
through them (two steps a cell: interact, step in). Lava is walkable and kills: a cell the text
places lava in is never entered, one it may be in costs more (much more next to the agent), but for
the cell behind an agent facing lava (it came from there: a move toward lava enters it). Water,
tables, furnaces, plants and creatures block.

Cells the text says nothing about count as free (the text names only the nearest thing of each kind);
the search covers the view and one ring beyond it (unseen, so free).
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

from illm_tools.oracles.crafter_reading import HALF_VIEW, STEPS, Cell, View

MOVES = tuple(STEPS)
"""The four moves, in crafter's action order (west, east, north, south): a heading is an index into it."""
DIRS = tuple(STEPS[m] for m in MOVES)
DONE = "done"
UNREACHABLE = 40.0
"""The cost of what cannot be done from here (more steps than any path in view)."""
RISK_NEXT, RISK_FAR = 12.0, 1.0
"""The extra cost of entering a cell that may be lava: next to the agent (a real risk: crafter lava
kills), and farther (the text will tell more when the agent is next to it)."""
UNSURE = 0.3
"""The extra cost of entering a cell that may hold something (a second tree, stone, water: the text
names the nearest of each kind only), so that a known way, or digging through a known stone, wins
over a guess."""
GRID = (HALF_VIEW[0] + 1, HALF_VIEW[1] + 1)
"""The search's reach: the view and one ring of unseen cells beyond it."""
GRID_CELLS = tuple((x, y) for x in range(-GRID[0], GRID[0] + 1) for y in range(-GRID[1], GRID[1] + 1))
GRID_SET = frozenset(GRID_CELLS)
PICKAXE = {"tree": None, "stone": "wood pickaxe", "coal": "wood pickaxe", "iron": "stone pickaxe",
           "diamond": "iron pickaxe"}
"""What the agent digs through, and the tool it needs (crafter's `collect` requirements)."""

State = tuple[int, int, int]


@dataclass(frozen=True)
class Goal:
    """Where a walk ends: facing one of `face` (the finishing action comes after), or standing on one of `reach`."""

    face: frozenset[Cell] = frozenset()
    reach: frozenset[Cell] = frozenset()
    through: bool = True
    """Whether it may dig through trees and the stone it has the pickaxe for."""


class Walk:
    """The steps left to a goal from every (cell, heading) of the grid (`left`), and each move's and
    interact's cost from where the agent stands (`first`)."""

    def __init__(self, view: View, goal: Goal):
        self.view, self.goal = view, goal
        kinds = view.kinds
        self.blocked: set[Cell] = set()
        self.deadly: set[Cell] = set()
        self.risk: dict[Cell, float] = {}
        self.removable: set[Cell] = set()
        for cell, (kind, maybe) in kinds.items():
            if kind == "lava":
                self.deadly.add(cell)
            elif kind is not None:
                self.blocked.add(cell)
                tool = PICKAXE.get(kind, "")
                if goal.through and kind in PICKAXE and (tool is None or view.has(tool)):
                    self.removable.add(cell)
            elif "lava" in maybe:
                self.risk[cell] = RISK_NEXT if abs(cell[0]) + abs(cell[1]) == 1 else RISK_FAR
            elif maybe:
                self.risk[cell] = UNSURE
        self.blocked |= {cell for cell in GRID_CELLS if cell not in kinds and cell != (0, 0) and view.beyond_edge(cell)}
        if view.facing == "lava" and view.facing_cell is not None:  # it walked here that way: behind is no lava
            self.risk.pop((-view.facing_cell[0], -view.facing_cell[1]), None)
        self.left = self._search()

    def inside(self, cell: Cell) -> bool:
        return cell in GRID_SET

    def step(self, state: State, action: int) -> tuple[State | str | None, float]:
        """Where an action (0-3 a move, 4 interact) takes a state, and its cost (steps, and the risk of
        stepping into lava); None: nowhere useful."""
        x, y, heading = state
        if action < 4:
            dx, dy = DIRS[action]
            q = (x + dx, y + dy)
            if q in self.goal.face:
                return (x, y, action), 1
            if q in self.deadly or not self.inside(q):
                return None, 1
            if q in self.blocked:
                return (x, y, action), 1
            return (DONE if q in self.goal.reach else (q[0], q[1], action)), 1 + self.risk.get(q, 0.0)
        dx, dy = DIRS[heading]
        q = (x + dx, y + dy)
        if q in self.goal.face:
            return DONE, 1
        if q in self.removable:
            return (DONE if q in self.goal.reach else (q[0], q[1], heading)), 2
        return None, 1

    def _search(self) -> dict:
        """Dijkstra backward from DONE over the reversed steps (`step`'s rules, written out per cell: a
        move's outcome does not depend on the heading it starts from)."""
        face, reach, blocked, deadly, removable, risk = (self.goal.face, self.goal.reach, self.blocked, self.deadly,
                                                         self.removable, self.risk)
        back: dict = {}
        for x, y in GRID_CELLS:
            if (x, y) in deadly or ((x, y) in blocked and (x, y) not in removable):
                continue
            for action, (dx, dy) in enumerate(DIRS):
                q = (x + dx, y + dy)
                if q in face:
                    to, cost = (x, y, action), 1.0
                    back.setdefault(DONE, []).append(((x, y, action), 1.0))  # interact facing it
                elif q in deadly or q not in GRID_SET:
                    continue
                elif q in blocked:
                    to, cost = (x, y, action), 1.0
                    if q in removable:  # interact facing it: dig, step in
                        back.setdefault(DONE if q in reach else (q[0], q[1], action), []).append(((x, y, action), 2.0))
                else:
                    to, cost = (DONE if q in reach else (q[0], q[1], action)), 1.0 + risk.get(q, 0.0)
                edges = back.setdefault(to, [])
                edges += [((x, y, h), cost) for h in range(4) if (x, y, h) != to]
        left = {DONE: 0.0}
        queue = [(0.0, 0, DONE)]
        order = 0
        while queue:
            d, _, node = heapq.heappop(queue)
            if d > left.get(node, UNREACHABLE):
                continue
            for prev, cost in back.get(node, ()):
                if d + cost < left.get(prev, UNREACHABLE):
                    left[prev] = d + cost
                    order += 1
                    heapq.heappush(queue, (d + cost, order, prev))
        return left

    def cost(self, state: State | str | None, steps: float) -> float:
        if state is None:
            return UNREACHABLE
        return float(min(steps + self.left.get(state, UNREACHABLE), UNREACHABLE))

    def first(self) -> dict[str, float]:
        """Each move's cost from the agent's cell (a move into a cell that may be lava: UNREACHABLE), and
        interact's where the agent's heading is told."""
        heading = -1
        if self.view.facing_cell is not None:
            heading = DIRS.index(self.view.facing_cell)
        out = {}
        for action, move in enumerate(MOVES):
            out[move] = self.cost(*self.step((0, 0, max(heading, 0)), action))
        if heading >= 0:
            to, steps = self.step((0, 0, heading), 4)
            if to is not None:
                out["interact"] = self.cost(to, steps)
        return out

    def path(self, best: str | None = None, limit: int = 7) -> list[str]:
        """The actions of a shortest walk from where the agent stands (starting with `best`, the
        planner's pick among equals), at most `limit`."""
        costs = self.first()
        if not costs or min(costs.values()) >= UNREACHABLE:
            return []
        best = best if best in costs else min(costs, key=costs.get)
        heading = DIRS.index(self.view.facing_cell) if self.view.facing_cell is not None else 0
        state: State | str | None = (0, 0, heading)
        out = []
        for _ in range(limit):
            if state == DONE or state is None:
                break
            options = {}
            for action in range(5):
                to, steps = self.step(state, action)  # type: ignore[arg-type]
                if to is not None and to != state:
                    options[action] = (self.cost(to, steps), to)
            if not out:
                action = MOVES.index(best) if best in MOVES else 4
            elif options:
                action = min(options, key=lambda a: options[a][0])
            else:
                break
            if action not in options:
                break
            out.append(MOVES[action] if action < 4 else "interact")
            state = options[action][1]
        return out
