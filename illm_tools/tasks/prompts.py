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
from json.encoder import encode_basestring
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

from illm_tools.keys import canonical_json, key_text, make_key
from illm_tools.errors import UsageError
from illm_tools.oracles.base import family_of
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
    family ("BabyAI", "MiniGrid", "MiniHack"; "Crafter" for CrafterReward-v1 / CrafterNoReward-v1),
    by the one rule the oracles are chosen by (`illm_tools.oracles.base.family_of`)."""
    return family_of(env_id)


def format_history(record: StateRecord) -> str:
    """Paper B.1: numbered observation/action pairs, oldest first, then the current observation."""
    return "".join(history_pieces(record))


def history_pieces(record: StateRecord) -> list[str]:
    """`format_history`'s text in pieces, in order: each line's label, then its observation (one line)
    or action. The keys escape it piece by piece, each distinct piece once (`StateKeys`)."""
    pieces = []
    for i, (obs, act) in enumerate(record.history):
        pieces += (observation_label(i), one_line(obs), action_label(i), act)
    pieces += (observation_label(len(record.history)), one_line(record.observation))
    return pieces


def observation_label(i: int) -> str:
    return f"\nObservation {i}: "


def action_label(i: int) -> str:
    return f"\nAction {i}: "


def one_line(text: str) -> str:
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
        """The keys of one state's tasks, in order (default: action key, summary key), the same as
        `key(render(task, record))` of each, computed without rendering the prompts
        (`StateKeys`: the trainer keys every step)."""
        return self._state_keys.keys(record, tasks)

    @cached_property
    def _state_keys(self) -> StateKeys:
        return StateKeys(self)


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
def _template_parts(name: str, directory: str | None = None) -> tuple[str, ...]:
    """The template's fixed text, split at each {field}."""
    return tuple(re.split(r"\{[a-z_]+\}", template_text(name, directory)))


def _fits(parts: tuple[str, ...], text: str) -> bool:
    """Whether `text` is `parts` with any text (the fields) between them: the first part at its
    start, the last at its end, the others in order between. Each middle part is placed at its first
    place after the one before (the earliest places leave the most room, so a fit exists exactly when
    this one fits): linear in the text, where a regular expression of wildcards backtracks (cubic
    with three fields: a 10 KB prompt of repeated template lines took 4 s)."""
    if len(parts) == 1:
        return text == parts[0]
    first, *middle, last = parts
    end = len(text) - len(last)
    if end < len(first) or not text.startswith(first) or not text.endswith(last):
        return False
    at = len(first)
    for part in middle:
        at = text.find(part, at, end)
        if at < 0:
            return False
        at += len(part)
    return True


def layouts_of(task: str, prompt: str) -> list[str]:
    """The layouts whose template for `task` could have rendered `prompt` (read from a cache row)."""
    spec = get_task(task)
    return [name for name in LAYOUTS if _fits(_template_parts(spec.templates[name][0], spec.template_dir), prompt)]


def neutral_prompt() -> str:
    """The context for PMI calibration: each candidate's log-prob after it is subtracted later."""
    return template_text("neutral")


# --- the keys of a state, without rendering its prompts -------------------------------------

_SENTINEL = "\x00illm-history\x00"
_FRAME_LIMIT = 200_000


def _escaped(text: str) -> str:
    """The JSON string body of `text` (what `json.dumps(ensure_ascii=False)` writes between the quotes)."""
    return encode_basestring(text)[1:-1]


class StateKeys:
    """`keys(record, tasks)`: the cache keys of a state's tasks, as `PromptBuilder.state_keys` returns
    them, computed without rendering its prompts; memoises its frames.

    Hand-written for speed: the trainer keys every task of every step of every rollout (two keys a
    step by default), and rendering both prompts, writing their canonical JSON and hashing it was
    most of a cached illm update's target look-up (benchmarks/keys.py; the figures are in
    docs/results/measured/trainer-pace.txt). A key hashes `key_text` of (setup, prompt,
    candidates). Here each (task, mission, valid actions) makes that text once with a sentinel for
    the history (its frame: the hash state up to the first history, the escaped text after each
    one), and a state's key copies the frame's hash and feeds it the state's escaped history (JSON
    escaping works character by character, so the escape of the prompt is the escapes of its pieces
    joined). The result is byte for byte `PromptBuilder.key(PromptBuilder.render(task, record))` (the
    tests compare them on awkward texts); a prompt whose history this cannot place (a sentinel in
    the mission, say) takes that generic path.
    """

    def __init__(self, builder):
        self.builder = builder
        self._frames: dict[tuple, tuple | None] = {}
        # a history's pieces, escaped and encoded: observations (one line), actions, each place's labels
        self._observations: dict[str, bytes] = {}
        self._actions: dict[str, bytes] = {}
        self._labels: list[tuple[bytes, bytes]] = []

    def _history(self, record: StateRecord) -> bytes:
        """`_escaped(format_history(record)).encode()`, put together from its pieces' escapes
        (`history_pieces`'s order): the labels' escapes made once per place, each distinct
        observation's (one line) and action's once; looked up by the texts themselves, whose hashes
        Python keeps (looking up each piece, the labels' new f-strings too, cost a state's keys
        5.6 us against 4.6: benchmarks/keys.py)."""
        observations, actions, labels = self._observations, self._actions, self._labels
        if len(observations) > _FRAME_LIMIT:
            observations.clear()
        steps = record.history
        while len(labels) <= len(steps):
            labels.append((_escaped(observation_label(len(labels))).encode(), _escaped(action_label(len(labels))).encode()))
        out = []
        for (obs, act), (obs_label, act_label) in zip(steps, labels):
            escaped_obs = observations.get(obs)
            if escaped_obs is None:
                escaped_obs = observations[obs] = _escaped(one_line(obs)).encode()
            escaped_act = actions.get(act)
            if escaped_act is None:
                escaped_act = actions[act] = _escaped(act).encode()
            out += (obs_label, escaped_obs, act_label, escaped_act)
        escaped_obs = observations.get(record.observation)
        if escaped_obs is None:
            escaped_obs = observations[record.observation] = _escaped(one_line(record.observation)).encode()
        out += (labels[len(steps)][0], escaped_obs)
        return b"".join(out)

    def _frame(self, task: str, record: StateRecord) -> tuple | None:
        """(hash state through the text before the first history, [escaped text after each history])
        of the record's task, mission and actions; None where the history cannot be placed."""
        b = self.builder
        prompt = b.render(task, record, history=_SENTINEL)
        text = key_text({"setup": b.setup_key(task), "prompt": prompt.text,
                         "candidates": list(prompt.candidates) if prompt.candidates is not None else None})
        parts = text.split(_escaped(_SENTINEL))
        if len(parts) < 2 or len(parts) - 1 != template_text(b.template(task)[0], get_task(task).template_dir).count("{history}"):
            return None  # no history field, or the sentinel elsewhere too
        return hashlib.sha256(parts[0].encode()), [p.encode() for p in parts[1:]]

    def keys(self, record: StateRecord, tasks: Sequence[str]) -> tuple[str, ...]:
        history = None
        out = []
        for task in tasks:
            slot = (task, record.mission, record.valid_actions)
            frame = self._frames.get(slot, False)
            if frame is False:
                if len(self._frames) > _FRAME_LIMIT:
                    self._frames.clear()
                frame = self._frames[slot] = self._frame(task, record)
            if frame is None:
                out.append(self.builder.task_key(task, record))
                continue
            if history is None:
                history = self._history(record)
            h = frame[0].copy()
            for piece in frame[1]:
                h.update(history)
                h.update(piece)
            out.append(h.hexdigest())
        return tuple(out)
