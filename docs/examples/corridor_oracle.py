"""An oracle for the corridor suite (`corridor_suite.py`) as an illm plug-in: `--backend oracle` then
annotates `Corridor-Walk-v0`'s states as a player who knows the corridor would.

One file: an `Oracle` subclass naming the games whose prompts it reads (the prompt's "playing
Corridor": the env id's family) and its version, then its three answers, read from the prompt's
text alone ("You are 3 steps from the goal"). The oracle backend turns the costs into a ranking,
noises a share of the states with `--oracle-noise`, embeds the texts and fingerprints the lot.
tests/test_oracles.py collects the corridor, annotates it with the oracle and reads the answers.
"""

from __future__ import annotations

import random
import re

from illm_tools.oracles.base import Oracle, Scene

_LEFT = re.compile(r"You are (\d+) steps? from the goal")


def steps_left(scene: Scene) -> int:
    """How far the goal is, from the current observation's text."""
    found = _LEFT.search(scene.observation)
    return int(found.group(1)) if found else 0


class CorridorOracle(Oracle):
    families = ("Corridor",)
    version = "corridor@1"  # part of every cache key of the oracle's answers: bump it when an answer changes

    def costs(self, scene: Scene) -> dict[str, float]:
        left = steps_left(scene)  # the steps left after each action
        return {a: left - 1 if a == "go right" else left + 1 for a in scene.actions}

    def text(self, scene: Scene, task: str) -> str:
        left = steps_left(scene)
        if task == "goal":
            return "reach the end of the corridor"
        if task == "plan":
            return ", ".join(["go right"] * min(left, 7))
        return f"The agent must reach the end of the corridor. The end is {left} steps to the right."

    def random_text(self, scene: Scene, task: str, rng: random.Random) -> str:
        words = [rng.choice(("go left", "go right")) for _ in range(rng.randint(1, 4))]
        return ", ".join(words) if task != "summary" else f"The agent must {words[0]}."
