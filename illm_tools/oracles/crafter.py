"""The Crafter oracle: the planner of `crafter_planner.py` (which reads Crafter-Text with
`crafter_reading.py` and walks the view with `crafter_paths.py`) behind the `Oracle` contract.

- costs: the planner's count of steps left in the step at hand after each action (walk to a tree,
  face it, interact; walk to a table, make a pickaxe; explore);
- texts: `summary` one fact a sentence ("The agent must collect wood. A tree is 3 steps north-east.
  It has 2 wood. Its drink is low."), `goal` the step at hand and the achievement tree's next two
  ("collect wood, place a table, make a wood pickaxe"), `plan` the next actions ("move north,
  move east, interact");
- random texts (the noised share of `oracle:noise=P`): a summary, goal and plan of random words of
  the same grammar.

It reads the current observation (and, when the prompt has a history, the last action: a move is
kept while exploring). Its version is the planner's ("crafter-planner@N" in the backend's fingerprint).
"""
from __future__ import annotations

import random

from illm_tools.oracles.base import PlannerOracle, Scene
from illm_tools.oracles.crafter_planner import PLANNER_VERSION, STRIKES, TOOLS, Answer, Planner, make_text
from illm_tools.oracles.crafter_reading import ACTIONS, FACE_PHRASES, ITEMS, KINDS, Seen, View, candidates, parse_view

_LOW = 3
"""A vital at or below this is said to be low."""


class CrafterOracle(PlannerOracle):
    """Crafter's oracle (see the module docstring); one planner, memoised per state."""

    families = ("Crafter",)
    version = f"crafter-planner@{PLANNER_VERSION}"
    planner_class = Planner

    def summary(self, scene: Scene, answer: Answer) -> str:
        return summary_text(parse_view(scene.observation), answer)

    def random_text(self, scene: Scene, task: str, rng: random.Random) -> str:
        return _random_text(task, rng)


def _things(count: int, item: str) -> str:
    return f"{count} {item}{'s' if count > 1 and item not in ('wood', 'stone', 'coal', 'iron') else ''}"


_PHRASES = {kind: phrase for phrase, kind in FACE_PHRASES.items()}


def _where(seen: Seen) -> str:
    """ "A tree is 3 steps north-east", "The edge of the world is 2 steps west": the renderer's phrase."""
    text = f"{_PHRASES[seen.kind]} is {seen.phrase}"
    return text[0].upper() + text[1:]


def summary_text(view: View, answer: Answer) -> str:
    """One fact a sentence: the step at hand, where its target is, what the agent has, its low vitals."""
    parts = [f"The agent must {answer.step.text}."]
    if view.sleeping:
        parts.append("It is asleep.")
    targets = [view.seen[k] for k in answer.step.kinds + answer.step.near if k in view.seen]
    if targets:
        parts += [f"{_where(t)}." for t in targets[:2]]
    elif answer.step.heading is not None:
        parts.append("Nothing it needs is in view.")
    if "zombie" in view.seen and "zombie" not in answer.step.kinds:
        parts.append(f"{_where(view.seen['zombie'])}.")
    held = [_things(n, i) for i, n in view.items.items() if n > 0]
    parts.append(f"It has {', '.join(held)}." if held else "It has nothing.")
    low = [v for v in ("health", "food", "drink", "energy") if view.vitals[v] <= _LOW]
    if low:
        parts.append(f"Its {' and '.join(low)} {'is' if len(low) == 1 else 'are'} low.")
    return " ".join(parts)


_STEPS = tuple(STRIKES.values()) + tuple(make_text(t) for t in TOOLS) + (
    "place a table", "place a furnace", "place stone", "place a sapling", "collect a sapling", "sleep",
    "find trees", "find stone", "find water", "find a cow", "find coal and iron")
_DIRECTIONS = ("north", "south", "east", "west", "north-east", "north-west", "south-east", "south-west")


def _random_text(task: str, rng: random.Random) -> str:
    """A random answer of the task's grammar (the noised share of `oracle:noise=P`)."""
    if task == "goal":
        return ", ".join(rng.sample(_STEPS, rng.randint(1, 3)))
    if task == "plan":
        return ", ".join(rng.choice(ACTIONS) for _ in range(rng.randint(1, 7)))
    parts = [f"The agent must {rng.choice(_STEPS)}."]
    if rng.random() < 0.7:
        dist = rng.randint(1, 7)
        where = rng.choice([d for d in _DIRECTIONS if candidates(dist, d)])
        parts.append(f"{_where(Seen(rng.choice(KINDS), dist, where, ()))}.")
    else:
        parts.append("Nothing it needs is in view.")
    held = rng.sample(ITEMS, rng.randint(0, 3))
    parts.append(f"It has {', '.join(_things(rng.randint(1, 9), i) for i in held)}." if held else "It has nothing.")
    if rng.random() < 0.3:
        parts.append(f"Its {rng.choice(('health', 'food', 'drink', 'energy'))} is low.")
    return " ".join(parts)
