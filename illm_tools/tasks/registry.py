"""The language tasks: what each asks the LLM, how its answer is decoded and stored, and how a
training run distils and pays for it.

Two kinds of task:
- `ranking`: the LLM scores each valid action after the prompt (`action`, the paper's action
  generation); the row keeps the candidates' log-probs and the run's head f^a learns the
  calibrated distribution (`illm_tools.tasks.calibration`);
- `text`: the LLM writes at most `max_new_tokens` tokens greedily; the row keeps the text and its
  embedding (the mean last hidden state over the generated tokens, `illm_tools.llm.generation`),
  which the task's own head learns (1 - cos) and whose disagreement it pays, "in the same fashion
  as the history compression head" (paper D.2). `summary` (history compression, B.2), `goal`
  (goal generation, D.2; ELLM's source of goals too, parsed by `parse_goals`) and `plan` (plan
  generation, D.2) are text tasks.

A task is one `LanguageTask` plus its template files (under `templates/`, or its own
`template_dir`); `register_task` adds one (a new task is that entry and its templates: prompts,
keys, annotation, the cache, the run's head, bonus and live fallback take it from here). Changing a template's text bumps its version;
changing how an answer is decoded or stored changes the task's `decoding`, which is part of
every key of the task.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from illm_tools.errors import UsageError
from illm_tools.registry import Registry

KINDS = ("ranking", "text")
NEUTRAL_VERSION = 1
"""Version of the neutral prompt of PMI calibration (templates/neutral.txt), in every ranking key."""


@dataclass(frozen=True)
class LanguageTask:
    """One language task (see the module docstring)."""

    name: str
    kind: str
    """`ranking` (score the valid actions) or `text` (greedy generation, embedded)."""
    templates: Mapping[str, tuple[str, int]]
    """Layout (`shared`, `paper`) -> (template file under templates/ without .txt, version)."""
    max_new_tokens: int = 0
    """text: the most tokens generated."""
    decoding_extra: Mapping[str, object] = field(default_factory=dict)
    """text: more decoding parameters in every key (a parser's version, ...)."""
    parse: Callable[[str, bool], list[str]] | None = None
    """text: (generated text, truncated) -> the row's `candidates` (the goal list), or None."""
    head: str = ""
    """Attribute name of the task's head on the policy network (f_a, f_hc, ...)."""
    weight_setting: str | None = None
    """The training setting holding the task's bonus weight (`lambda_a`, `beta_hc`); None: the
    run's `task_weights[name]`, default `DEFAULT_WEIGHT`."""
    template_dir: str | None = None
    """Folder of the template files (None: illm_tools/tasks/templates); a task registered from
    elsewhere brings its own. Only the file's name and version enter the keys."""
    hop: bool = True
    """Whether the task has a hop form (its prompt with the translated window spliced in)."""
    description: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"task {self.name}: kind must be one of {KINDS}, got {self.kind!r}")
        if self.kind == "text" and self.max_new_tokens <= 0:
            raise ValueError(f"task {self.name}: a text task needs max_new_tokens > 0")
        if not self.head:
            object.__setattr__(self, "head", f"f_{self.name}")

    def decoding(self) -> dict:
        """The decoding parameters every key of the task carries."""
        if self.kind == "ranking":
            return {"method": "candidate-logprob", "neutral": f"neutral@{NEUTRAL_VERSION}"}
        return {"method": "greedy", "max_new_tokens": self.max_new_tokens, **self.decoding_extra}


DEFAULT_WEIGHT = 0.5
"""Bonus weight of a text task without a setting of its own (goal, plan): beta_hc's paper value,
as their heads are trained like the history-compression head (D.2)."""

LANGUAGE_TASKS: Registry[LanguageTask] = Registry("language task", "illm.tasks", check=LanguageTask, hint="--tasks")
"""Every language task by name (what `--tasks` accepts), in registration order; installed packages
add theirs through `illm.tasks` entry points (each a `LanguageTask` with its own `template_dir`)."""

DEFAULT_TASKS = ("action", "summary")
"""The tasks annotated and distilled when none are named: iLLM's two (paper: 2 tasks by default)."""


def register_task(task: LanguageTask) -> LanguageTask:
    """Add a task (its templates must exist under templates/ or its `template_dir`); refuses a
    second task of one name."""
    return LANGUAGE_TASKS.register(task.name, task)


def get_task(name: str) -> LanguageTask:
    return LANGUAGE_TASKS.load(name)


def parse_tasks(tasks, option: str = "--tasks") -> tuple[str, ...]:
    """Task names from "action,summary" (or "action+summary", as the paper's Table 2 writes them and
    as experiment labels keep them) or a sequence, checked, duplicates dropped, in the given order."""
    names = [t.strip() for t in (tasks.replace("+", ",").split(",") if isinstance(tasks, str) else tasks)
             if t and t.strip()]
    unknown = [t for t in names if t not in LANGUAGE_TASKS]
    if unknown or not names:
        raise UsageError(f"unknown {option} {','.join(unknown) or '(none)'}: choose any of {','.join(LANGUAGE_TASKS)}")
    return tuple(dict.fromkeys(names))


def text_tasks(tasks) -> tuple[str, ...]:
    """The text tasks among `tasks`, in order (each a D-wide block of a run's embedding targets)."""
    return tuple(t for t in tasks if get_task(t).kind == "text")


def _register_builtin() -> None:
    from illm_tools.tasks.goals import GOAL_PARSER_VERSION, parse_goals

    register_task(LanguageTask(
        "action", "ranking", {"paper": ("action.paper", 2), "shared": ("action.shared", 1)}, head="f_a",
        weight_setting="lambda_a", description="action generation: the LLM's ranking of the valid actions (B.2)"))
    register_task(LanguageTask(
        "summary", "text", {"paper": ("summary", 1), "shared": ("summary", 1)}, max_new_tokens=64, head="f_hc",
        weight_setting="beta_hc", description="history compression: a 64-token summary of the recent history (B.2)"))
    # goal.txt is D.2's goal prompt as printed (its instruction in one line) plus a last line
    # "Goals:", the cue after which the model writes its list. Its rows keep the raw text, the
    # parsed goals (ELLM) and, since "embedding" joined its decoding, the text's embedding (iLLM).
    register_task(LanguageTask(
        "goal", "text", {"paper": ("goal", 1), "shared": ("goal", 1)}, max_new_tokens=32,
        decoding_extra={"parse": f"goals@{GOAL_PARSER_VERSION}", "embedding": "mean-last-hidden@1"},
        parse=parse_goals, description="goal generation: goals to reach next (D.2; ELLM's goals)"))
    # plan.txt is D.2's plan prompt as printed (in one line) plus a last line "Plan:". 48 tokens
    # hold the 2-7 short actions it asks for.
    register_task(LanguageTask(
        "plan", "text", {"paper": ("plan", 1), "shared": ("plan", 1)}, max_new_tokens=48,
        description="plan generation: a sequence of 2-7 actions (D.2)"))


_register_builtin()
