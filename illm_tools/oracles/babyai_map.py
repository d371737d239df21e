"""The view's geometry for the BabyAI oracle's planner (`illm_tools.oracles.babyai_planner`): which cells of
the 7x7 view the agent can stand on (`Map`, read from the text as the planner's docstring says),
breadth-first distances over (cell, heading), and the moves along them. Split from the planner,
which decides what to do; this only says where the agent can go."""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

from illm_tools.oracles.babyai_reading import View

HALF_VIEW, DEPTH = 3, 7
"""The view: x in [-HALF_VIEW, HALF_VIEW], y in [0, DEPTH)."""

# heading 0 is forward (+y), 1 right (+x), 2 back, 3 left
_STEP = ((0, 1), (1, 0), (0, -1), (-1, 0))
_FREE_KINDS = ("goal", "floor")
UNREACHABLE = 99.0
MOVES = ("turn left", "turn right", "go forward")


# --- the map of the view ----------------------------------------------------------------------------
class Map:
    """Which cells of the view the agent can stand on."""

    def __init__(self, view: View):
        self.view = view
        self.blocked: set[tuple[int, int]] = set()
        beyond = {"forward": False, "left": False, "right": False}
        fwd, left, right = view.walls
        for t in view.things:
            beyond["forward"] |= fwd is not None and t.y > fwd
            beyond["left"] |= left is not None and t.x < -left
            beyond["right"] |= right is not None and t.x > right
        if fwd is not None or left is not None or right is not None:
            for x in range(-HALF_VIEW, HALF_VIEW + 1):
                for y in range(DEPTH):
                    if ((fwd is not None and (y > fwd or (y == fwd and (x == 0 or not beyond["forward"]))))
                            or (left is not None and (x < -left or (x == -left and (y == 0 or not beyond["left"]))))
                            or (right is not None and (x > right or (x == right and (y == 0 or not beyond["right"]))))):
                        self.blocked.add((x, y))
        for t in view.things:  # what stands in a cell decides it, wall line or not
            if (t.state != "open") if t.kind == "door" else (t.kind not in _FREE_KINDS):
                self.blocked.add((t.x, t.y))
            else:
                self.blocked.discard((t.x, t.y))

    @staticmethod
    def inside(x: int, y: int) -> bool:
        return -HALF_VIEW <= x <= HALF_VIEW and 0 <= y < DEPTH

    def free(self, x: int, y: int) -> bool:
        return self.inside(x, y) and (x, y) not in self.blocked

    def distances(self, goals: set[tuple[int, int, int]]) -> dict[tuple[int, int, int], int]:
        """Actions (turns and forward steps) from each (x, y, heading) to the nearest goal state: a
        breadth-first search backwards from the goals (the planner's hot path: kept to plain loops)."""
        blocked = self.blocked
        dist = dict.fromkeys(goals, 0)
        queue = deque(goals)
        while queue:
            state = queue.popleft()
            x, y, h = state
            d = dist[state] + 1
            dx, dy = _STEP[h]
            px, py = x - dx, y - dy
            for p in ((x, y, (h + 1) % 4), (x, y, (h - 1) % 4),  # turned left / right into heading h
                      (px, py, h) if -HALF_VIEW <= px <= HALF_VIEW and 0 <= py < DEPTH and (px, py) not in blocked
                      else None):
                if p is not None and p not in dist:
                    dist[p] = d
                    queue.append(p)
        return dist

    def facing(self, cells: Sequence[tuple[int, int]]) -> set[tuple[int, int, int]]:
        """The states that face one of `cells` from a free neighbour."""
        out = set()
        for cx, cy in cells:
            for h, (dx, dy) in enumerate(_STEP):
                if self.free(cx - dx, cy - dy):
                    out.add((cx - dx, cy - dy, h))
        return out


def _successor(state: tuple[int, int, int], action: str, grid: Map) -> tuple[int, int, int]:
    x, y, h = state
    if action == "turn left":
        return x, y, (h - 1) % 4
    if action == "turn right":
        return x, y, (h + 1) % 4
    dx, dy = _STEP[h]
    return (x + dx, y + dy, h) if grid.free(x + dx, y + dy) else state


def _path(dist: dict, grid: Map, start=(0, 0, 0), limit: int = 7) -> list[str]:
    """The moves along the distance field from `start` (greedy descent, forward first on ties)."""
    out, state = [], start
    while dist.get(state, 0) > 0 and len(out) < limit:
        step = min(("go forward", "turn left", "turn right"),
                   key=lambda a: dist.get(_successor(state, a, grid), UNREACHABLE))
        out.append(step)
        state = _successor(state, step, grid)
    return out
