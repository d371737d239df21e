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

Three tasks: `action` (score the valid actions) and `summary` (64-token history compression) are
iLLM's and the default everywhere; `goal` is ELLM's (Du et al. 2023, "Guiding Pretraining in
Reinforcement Learning with Large Language Models"): the LLM suggests goals for the state, with the
goal-generation prompt of the paper's Appendix D.2, generated greedily like the summary and parsed
into a list of goal strings by `parse_goals` (see there; the raw text is kept beside the list).
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

from illm_tools.cache.keys import canonical_json, make_key
from illm_tools.errors import UsageError
from illm_tools.tasks.state import StateRecord

TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"
TASKS = ("action", "summary", "goal")
"""Every language task (what `--tasks` accepts)."""
DEFAULT_TASKS = ("action", "summary")
"""The tasks annotated when none are named: iLLM's two (the `goal` task is asked for by name)."""
LAYOUTS = ("shared", "paper")
# (task, layout) -> (template file, version). Bump the version when the file's text changes.
# Both layouts use the same summary prompt, so their summary keys (and cache rows) coincide; so
# do their goal prompts. goal.txt is the goal-generation prompt of the paper's Appendix D.2 as
# printed (its instruction joined into one line, as the other templates are), plus a last line
# "Goals:" that the paper does not print: the cue after which the model writes its list (as
# "Answer:" ends the action prompt).
TEMPLATES = {
    ("action", "paper"): ("action.paper", 1),
    ("action", "shared"): ("action.shared", 1),
    ("summary", "paper"): ("summary", 1),
    ("summary", "shared"): ("summary", 1),
    ("goal", "paper"): ("goal", 1),
    ("goal", "shared"): ("goal", 1),
}
NEUTRAL_VERSION = 1
SUMMARY_TOKENS = 64
GOAL_TOKENS = 32
"""New tokens generated for a goal list: a few short phrases (the summary's 64 cost twice as much,
and greedy decoding dominates annotation time)."""
GOAL_PARSER_VERSION = 1
"""Version of `parse_goals`: part of the goal task's decoding parameters, so of every goal key
(the parsed list is stored in the row). Bump it when the parsing changes."""
MAX_GOALS = 8
"""Goals kept per state (the first ones the model wrote)."""
MAX_GOAL_WORDS = 8
"""Longer items are not "a single valid word or a phrase" (the prompt's words) and are dropped."""


@lru_cache(maxsize=None)
def template_text(name: str) -> str:
    return (TEMPLATE_DIR / f"{name}.txt").read_text().rstrip("\n")


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
        return TEMPLATES[(task, self.layout)]

    def decoding(self, task: str) -> dict:
        if task == "action":
            return {"method": "candidate-logprob", "neutral": f"neutral@{NEUTRAL_VERSION}"}
        if task == "goal":
            return {"method": "greedy", "max_new_tokens": GOAL_TOKENS, "parse": f"goals@{GOAL_PARSER_VERSION}"}
        return {"method": "greedy", "max_new_tokens": SUMMARY_TOKENS}

    def task_line(self, record: StateRecord) -> str:
        return f"{game_of(self.env_id)}. The goal is: {record.mission}."

    def render(self, task: str, record: StateRecord, history: str | None = None) -> Prompt:
        """The task's prompt for a state; `history` is `format_history(record)` when the caller
        already has it (both tasks of a state share it)."""
        if task not in TASKS:
            raise UsageError(f"unknown language task {task!r}: use one of {', '.join(TASKS)}")
        history = format_history(record) if history is None else history
        fields = {"task": self.task_line(record), "history": history, "actions": ", ".join(record.valid_actions)}
        text = template_text(self.template(task)[0]).format(**fields)
        candidates = tuple(" " + a for a in record.valid_actions) if task == "action" else None
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
    def _setup_keys(self) -> dict[str, str]:
        keys = {}
        for task in TASKS:
            template, version = self.template(task)
            keys[task] = make_key(task=task, template=template, template_version=version, renderer=self.renderer,
                                  model_fingerprint=self.model_fingerprint, decoding=self.decoding(task))
        return keys

    def key(self, prompt: Prompt) -> str:
        """The cache key: the task's setup digest plus the rendered prompt and candidates."""
        return make_key(setup=self.setup_key(prompt.task), prompt=prompt.text,
                        candidates=list(prompt.candidates) if prompt.candidates is not None else None)

    def task_key(self, task: str, record: StateRecord, history: str | None = None) -> str:
        """The cache key of one task of one state (e.g. the `goal` row the ELLM bonus reads)."""
        return self.key(self.render(task, record, history))

    def state_keys(self, record: StateRecord) -> tuple[str, str]:
        """(action key, summary key) of one state, its history rendered once."""
        history = format_history(record)
        return (self.key(self.render("action", record, history)), self.key(self.render("summary", record, history)))


@lru_cache(maxsize=None)
def _template_pattern(name: str) -> re.Pattern:
    """The template's fixed text with each {field} as a wildcard."""
    parts = re.split(r"\{[a-z_]+\}", template_text(name))
    return re.compile(".*?".join(re.escape(p) for p in parts), re.DOTALL)


def layouts_of(task: str, prompt: str) -> list[str]:
    """The layouts whose template for `task` could have rendered `prompt` (read from a cache row)."""
    return [layout for layout in LAYOUTS if _template_pattern(TEMPLATES[(task, layout)][0]).fullmatch(prompt)]


def neutral_prompt() -> str:
    """The context for PMI calibration: each candidate's log-prob after it is subtracted later."""
    return template_text("neutral")


# ---- the goal task's answer ---------------------------------------------------------------------

_PROMPT_LINE = re.compile(r"(you are an expert player|recent player's history|valid actions|suggest the next goal"
                          r"|observation \d+\s*:|action \d+\s*:)", re.IGNORECASE)
_INLINE_NUMBER = re.compile(r"\s(?=\d{1,2}[.)]\s)")
_MARKER = re.compile(r"^(?:[-*\u2022]+|\(?\d{1,2}[.):])\s*")
_LABEL = re.compile(r"^(?:next\s+)?goals?(?:\s*\d+)?\s*[:\-]\s*", re.IGNORECASE)
_QUOTES = "\"'`\u201c\u201d\u2018\u2019()[]{}<> "
_COPIES = ("you see ", "you carry ")


def parse_goals(text: str, truncated: bool = False) -> list[str]:
    """The goal strings of a generated answer to the `goal` prompt (version `GOAL_PARSER_VERSION`);
    `truncated`: the generation was cut at `GOAL_TOKENS` (not ended by the model).

    1. Lines are read in order; a blank line after the first goal, or a line that starts a prompt
       of its own ("You are an expert player", "Recent player's history", "Observation N:",
       "Action N:", "Valid actions", "Suggest the next goal"), ends the list: small models go on
       writing the prompt again.
    2. Each line is split into items at commas, semicolons and inline numbering ("1. a 2. b").
    3. Each item loses a leading list marker ("-", "*", "\u2022", "1.", "2)"), a label ("Goal:",
       "Goals:", "Goal 1:"), quotes and brackets around it, and trailing ".", "!", "?", ":"; its
       whitespace is collapsed and it is lower-cased.
    4. Dropped: empty items, items without a letter, items longer than `MAX_GOAL_WORDS` words (not
       "a single valid word or a phrase", the prompt's words), and copies of the observation
       ("you see ...", "you carry ...").
    5. In a truncated generation whose list did not end before the cut (by 1.), the last item is
       dropped: it may be cut mid-phrase ("- Open door\n- Open").
    6. Duplicates are dropped (first kept) and at most `MAX_GOALS` goals are returned.
    """
    items: list[str] = []
    ended = False
    for line in text.splitlines():
        if not line.strip():
            if items:
                ended = True
                break
            continue
        if _PROMPT_LINE.match(_MARKER.sub("", line.strip())):
            ended = True
            break
        items += re.split(r"[,;]", _INLINE_NUMBER.sub(";", line))
    if truncated and not ended:
        items = items[:-1]
    goals: list[str] = []
    for item in items:
        goal = _clean_goal(item)
        if goal and goal not in goals:
            goals.append(goal)
    return goals[:MAX_GOALS]


def _clean_goal(item: str) -> str | None:
    """One list item as a goal (steps 3 and 4 of `parse_goals`), None when it is not one."""
    goal = _MARKER.sub("", item.strip())
    goal = _LABEL.sub("", goal)
    goal = " ".join(goal.strip(_QUOTES).rstrip(".!?:").strip(_QUOTES).split()).lower()
    if not goal or not re.search(r"[a-z]", goal) or len(goal.split()) > MAX_GOAL_WORDS:
        return None
    if goal.startswith(_COPIES):
        return None
    return goal
