"""Language tasks: versioned prompt templates (paper Appendix B.2), the history format (B.1), and
the named inputs that make a cache key. `illm annotate` and `illm train` both build prompts and
keys here, so a state seen by the trainer finds the row the annotator wrote.

Two template layouts:
- `paper`: the paper's prompts as printed (the action prompt lists the valid actions before the
  history, so the two tasks share only their first line);
- `shared` (default): the same wording with the history first in both prompts, so the prefix
  "You are an expert player playing ... Recent player's history: ..." is computed once for both
  tasks (see illm_tools.annotate).
Changing a template's text must bump its version (tests pin each version's text hash).

The tasks themselves (action, summary, goal, plan: what each asks, how it is decoded, its head
and bonus weight) are registered in `illm_tools.tasks.registry`; the goal parser is in
`illm_tools.tasks.goals` (re-exported here).
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

from illm_tools.keys import canonical_json, make_key
from illm_tools.errors import UsageError
from illm_tools.tasks.registry import DEFAULT_TASKS, LANGUAGE_TASKS, get_task  # noqa: F401
from illm_tools.tasks.state import StateRecord

TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"
LAYOUTS = ("shared", "paper")
SUMMARY_TOKENS = LANGUAGE_TASKS["summary"].max_new_tokens
"""The paper's L = 64 tokens of a summary."""


@lru_cache(maxsize=None)
def template_text(name: str, directory: str | None = None) -> str:
    """The text of template `name` (a file `name`.txt under `directory`, default templates/)."""
    return (Path(directory or TEMPLATE_DIR) / f"{name}.txt").read_text().rstrip("\n")


def template_sha(name: str) -> str:
    return hashlib.sha256(template_text(name).encode()).hexdigest()[:16]


def game_of(env_id: str) -> str:
    """The game named in the prompt's "You are an expert player playing {task}": the env id's
    family ("BabyAI", "MiniGrid", "MiniHack"; "Crafter" for CrafterReward-v1 / CrafterNoReward-v1)."""
    family = env_id.split("-", 1)[0]
    return "Crafter" if family.startswith("Crafter") else family


def format_history(record: StateRecord) -> str:
    """Paper B.1: numbered observation/action pairs, oldest first, then the current observation."""
    lines = []
    for i, (obs, act) in enumerate(record.history):
        lines.append(f"Observation {i}: {_one_line(obs)}")
        lines.append(f"Action {i}: {act}")
    lines.append(f"Observation {len(record.history)}: {_one_line(record.observation)}")
    return "\n" + "\n".join(lines)


def _one_line(text: str) -> str:
    if "\n" not in text and "\r" not in text:  # renderers write one line: the hot path
        return text.strip() or "nothing"
    return ", ".join(part.strip() for part in text.splitlines() if part.strip()) or "nothing"


@dataclass(frozen=True)
class Prompt:
    """A rendered prompt and the parts it was made of."""

    task: str
    text: str
    goal: str
    history: str
    observation: str
    candidates: tuple[str, ...] | None


@dataclass(frozen=True)
class PromptBuilder:
    """Renders one env's states into the prompts of the language tasks, and keys them.

    `model_fingerprint` is the hash of the model's named fingerprint inputs; `renderer` the
    env's text renderer (name@version). Decoding parameters are part of every key.
    """

    env_id: str
    renderer: str
    model_fingerprint: str
    model: str
    history_len: int = 3
    layout: str = "shared"

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise UsageError(f"unknown template layout {self.layout!r}: use one of {', '.join(LAYOUTS)}")
        if self.history_len < 0:
            raise UsageError(f"--history must be 0 or more, got {self.history_len}")

    def template(self, task: str) -> tuple[str, int]:
        """(template file name, version) of a task in this layout."""
        return get_task(task).templates[self.layout]

    def decoding(self, task: str) -> dict:
        return get_task(task).decoding()

    def task_line(self, record: StateRecord) -> str:
        return f"{game_of(self.env_id)}. The goal is: {record.mission}."

    def render(self, task: str, record: StateRecord, history: str | None = None) -> Prompt:
        """The task's prompt for a state; `history` is `format_history(record)` when the caller
        already has it (both tasks of a state share it)."""
        ranking = get_task(task).kind == "ranking"
        history = format_history(record) if history is None else history
        fields = {"task": self.task_line(record), "history": history, "actions": ", ".join(record.valid_actions)}
        text = template_text(self.template(task)[0], get_task(task).template_dir).format(**fields)
        candidates = tuple(" " + a for a in record.valid_actions) if ranking else None
        return Prompt(task, text, record.mission, history, record.observation, candidates)

    def setup(self, task: str) -> dict:
        """The named inputs every key of a task shares, in the cache's column names (plus the layout)."""
        return {"task": task, "template_version": self.template(task)[1], "renderer": self.renderer,
                "model_fingerprint": self.model_fingerprint, "decoding": canonical_json(self.decoding(task)),
                "history_len": self.history_len, "layout": self.layout}

    def setup_key(self, task: str) -> str:
        """Digest of every named input that is the same for all states of a task: task, template
        and version, renderer, model fingerprint, decoding parameters."""
        return self._setup_keys[task]

    @cached_property
    def _setup_keys(self) -> _SetupKeys:
        return _SetupKeys(self)

    def key(self, prompt: Prompt) -> str:
        """The cache key: the task's setup digest plus the rendered prompt and candidates."""
        return make_key(setup=self.setup_key(prompt.task), prompt=prompt.text,
                        candidates=list(prompt.candidates) if prompt.candidates is not None else None)

    def task_key(self, task: str, record: StateRecord, history: str | None = None) -> str:
        """The cache key of one task of one state (e.g. the `goal` row the ELLM bonus reads)."""
        return self.key(self.render(task, record, history))

    def state_keys(self, record: StateRecord, tasks: Sequence[str] = DEFAULT_TASKS) -> tuple[str, ...]:
        """The keys of one state's tasks, in order (default: action key, summary key), its history
        rendered once."""
        history = format_history(record)
        return tuple(self.key(self.render(task, record, history)) for task in tasks)


class _SetupKeys(dict):
    """A builder's setup digests, computed per task on first use (tasks registered later count)."""

    def __init__(self, builder: PromptBuilder):
        super().__init__()
        self.builder = builder

    def __missing__(self, task: str) -> str:
        b = self.builder
        template, version = b.template(task)
        self[task] = key = make_key(task=task, template=template, template_version=version, renderer=b.renderer,
                                    model_fingerprint=b.model_fingerprint, decoding=b.decoding(task))
        return key


@lru_cache(maxsize=None)
def _template_pattern(name: str, directory: str | None = None) -> re.Pattern:
    """The template's fixed text with each {field} as a wildcard."""
    parts = re.split(r"\{[a-z_]+\}", template_text(name, directory))
    return re.compile(".*?".join(re.escape(p) for p in parts), re.DOTALL)


def layouts_of(task: str, prompt: str) -> list[str]:
    """The layouts whose template for `task` could have rendered `prompt` (read from a cache row)."""
    spec = get_task(task)
    return [layout for layout in LAYOUTS if _template_pattern(spec.templates[layout][0], spec.template_dir).fullmatch(prompt)]


def neutral_prompt() -> str:
    """The context for PMI calibration: each candidate's log-prob after it is subtracted later."""
    return template_text("neutral")
