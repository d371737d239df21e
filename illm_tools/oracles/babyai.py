"""The BabyAI and MiniGrid oracle: the rule-based planner of `babyai_planner.py` (which reads the
view with `babyai_reading.py` and walks it with `babyai_map.py`) behind the `Oracle` contract.

- costs: the planner's count of steps left after each valid action;
- texts: `summary` a short account of the history (the step at hand, what the agent did, where the
  step's objects are, what it carries, what blocks it), `goal` the step at hand and those after it
  ("pick up the yellow key, open the door"), `plan` the next actions ("go forward, turn left,
  pick up");
- random texts (the noised share): a summary, goal and plan of random words of the same grammar.

Its version is the planner's (`PLANNER_VERSION`, "planner@N" in the oracle backend's fingerprint).
"""

from __future__ import annotations

import random

from illm_tools.oracles.babyai_planner import COLOURS, GAMES, MOVES, PLANNER_VERSION, Planner, summary_text
from illm_tools.oracles.base import PlannerOracle, Scene


class BabyAIOracle(PlannerOracle):
    """BabyAI's and MiniGrid's oracle (see the module docstring); one planner, memoised per state."""

    families = GAMES
    version = f"planner@{PLANNER_VERSION}"
    planner_class = Planner

    def summary(self, scene: Scene, answer) -> str:
        return summary_text(scene, answer)

    def random_text(self, scene: Scene, task: str, rng: random.Random) -> str:
        return _random_text(task, rng, len(scene.history))


_VERBS = ("go to", "pick up", "open", "put")
_KINDS = ("key", "ball", "box", "door")
_PLACES = ("adjacent in front", "near, ahead", "near, ahead on the left", "near, ahead on the right", "far, ahead",
           "far, ahead on the left", "far, ahead on the right", "near to the left", "near to the right")


def _random_text(task: str, rng: random.Random, history: int) -> str:
    """A random answer of the task's grammar (the noised share of `--oracle-noise`)."""
    def thing() -> str:
        return f"{rng.choice(COLOURS)} {rng.choice(_KINDS)}"

    def step() -> str:
        verb = rng.choice(_VERBS)
        return f"put the {thing()} next to the {thing()}" if verb == "put" else f"{verb} the {thing()}"

    if task == "goal":
        return ", ".join(step() for _ in range(rng.randint(1, 2)))
    if task == "plan":
        return ", ".join(rng.choice(MOVES + ("pick up", "drop", "toggle")) for _ in range(rng.randint(2, 7)))
    parts = [f"The agent must {step()}."]
    if history:
        parts.append(f"It {', then '.join(rng.choice(('turned left', 'turned right', 'went forward')) for _ in range(history))}.")
    parts.append(f"The {thing()} is {rng.choice(_PLACES)}." if rng.random() < 0.7 else "Nothing it needs is in view.")
    parts.append(f"It carries a {thing()}." if rng.random() < 0.3 else "It carries nothing.")
    return " ".join(parts)
