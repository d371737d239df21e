"""What an oracle of one suite implements (`Oracle`), and the prompt's frame every oracle reads
(`parse_prompt` into a `Scene`; `family_of`, the game an env id's prompts name).

An oracle is an annotator that knows one family of games, the positive control of iLLM where no
language model knows the game. It reads the prompt an LLM is given and nothing else (this package
sits below `envs/` in the import layers: it cannot read an environment): the first line names the
game and the mission ("You are an expert player playing BabyAI. The goal is: open the red door."),
then the history ("Observation i: ...", "Action i: ...", oldest first; the last observation is the
current one) and, for the action task, the valid actions ("Valid actions: turn left, ...").

Given a `Scene`, an oracle gives each valid action a cost (`costs`: the steps left after taking it,
lower is better) and writes the text tasks' answers (`text`: summary, goal, plan), and for the
quality knob a random answer of its own grammar (`random_text`). What is the same for every oracle
is the oracle backend's (`illm_tools.llm.oracle`): costs turned into log-probabilities, which states
are noised, the answers' embeddings, the fingerprint. Which oracle answers a state is the
registry's (`illm_tools.oracles.registry`), by the game the prompt names.
"""

from __future__ import annotations

import random
import re
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar


def family_of(env_id: str) -> str:
    """The game a prompt about an env id's states names ("You are an expert player playing {family}"):
    the id's family ("BabyAI", "MiniGrid", "MiniHack"; "Crafter" for CrafterReward-v1 and
    CrafterNoReward-v1). The prompt writes it (`illm_tools.tasks.prompts.game_of`), oracles are
    chosen by it."""
    family = env_id.split("-", 1)[0]
    return "Crafter" if family.startswith("Crafter") else family


# --- the prompt's frame ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Scene:
    """What one prompt says: game, mission, history pairs (observation, action) and the current
    observation, and the valid actions (empty where the prompt lists none: the text tasks)."""

    game: str
    mission: str
    history: tuple[tuple[str, str], ...]
    observation: str
    actions: tuple[str, ...]

    @property
    def state_id(self) -> str:
        """What determines the state, whatever the task asking about it."""
        parts = [self.game, self.mission, *(f"{o}\x1e{a}" for o, a in self.history), self.observation]
        return "\x1f".join(parts)


class NotAScene(ValueError):
    """The text is not a prompt about a state (not one `illm_tools.tasks.prompts` renders)."""


_FIRST = re.compile(r"You are an expert player playing (?P<game>.+?)\. The goal is: (?P<mission>.*?)\.?\s*$")
_OBS = re.compile(r"^Observation (\d+): (.*)$")
_ACT = re.compile(r"^Action (\d+): (.*)$")
_VALID = re.compile(r"^Valid actions: (.*)$")


def parse_prompt(text: str) -> Scene:
    """The scene of a prompt rendered by `illm_tools.tasks.prompts` (any task, either layout)."""
    lines = text.splitlines()
    first = _FIRST.match(lines[0]) if lines else None
    if first is None:
        raise NotAScene("the prompt does not start with 'You are an expert player playing GAME. The goal is: ...'")
    observations: dict[int, str] = {}
    actions: dict[int, str] = {}
    valid: tuple[str, ...] = ()
    for line in lines[1:]:
        if m := _OBS.match(line):
            observations[int(m.group(1))] = m.group(2).strip()
        elif m := _ACT.match(line):
            actions[int(m.group(1))] = m.group(2).strip()
        elif m := _VALID.match(line):
            valid = tuple(a.strip() for a in m.group(1).split(",") if a.strip())
    if not observations:
        raise NotAScene("the prompt holds no 'Observation N:' line")
    last = max(observations)
    history = tuple((observations[i], actions.get(i, "")) for i in range(last) if i in observations)
    return Scene(first.group("game").strip(), first.group("mission").strip(), history, observations[last], valid)


# --- the contract ------------------------------------------------------------------------------------
class Oracle(ABC):
    """The oracle of one suite. The backend makes one per run (`Oracle()`, no arguments): it may keep
    a memo of its own, never state that changes an answer."""

    families: ClassVar[tuple[str, ...]] = ()
    """The games whose prompts it reads, as prompts name them (`family_of`): ("BabyAI", "MiniGrid")."""
    version: ClassVar[str] = ""
    """Its rules' name and version ("planner@1"): part of the oracle backend's fingerprint, so of every
    cache key of the oracle's answers. CHANGING ANY ANSWER IT GIVES MUST BUMP IT."""

    @abstractmethod
    def costs(self, scene: Scene) -> dict[str, float]:
        """Each of `scene.actions`' cost: the steps left after taking it (lower is better). The backend
        ranks by log softmax(-KAPPA * cost): a step worse is e^-2 as likely."""

    @abstractmethod
    def text(self, scene: Scene, task: str) -> str:
        """The answer of a text task: "summary" (one fact a sentence, "The agent must ... It carries
        nothing.": its embedding is the mean of its sentences'), "goal" or "plan"; any other task
        gets the summary."""

    @abstractmethod
    def random_text(self, scene: Scene, task: str, rng: random.Random) -> str:
        """A random answer of the task's grammar drawn from `rng` alone (`--oracle-noise`'s share)."""


class PlannerOracle(Oracle):
    """An oracle whose answers are one planner's: `planner_class()` made once, its `answer(scene)`
    (memoised per state by the planner) holding `costs`, `goal` and `plan` (the next actions' names).
    The goal and plan tasks are those, the plan joined with ", " ("look around" when empty); the
    summary is the oracle's own (`summary`). The three suites' oracles share this shape."""

    planner_class: ClassVar[type]

    def __init__(self) -> None:
        self.planner = self.planner_class()

    def costs(self, scene: Scene) -> dict[str, float]:
        return self.planner.answer(scene).costs

    def text(self, scene: Scene, task: str) -> str:
        answer = self.planner.answer(scene)
        if task == "goal":
            return answer.goal
        if task == "plan":
            return ", ".join(answer.plan) if answer.plan else "look around"
        return self.summary(scene, answer)

    @abstractmethod
    def summary(self, scene: Scene, answer) -> str:
        """The summary task's answer, one fact a sentence, from the planner's answer."""
