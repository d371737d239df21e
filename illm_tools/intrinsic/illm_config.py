"""`ILLMConfig`: iLLM's own settings (its heads' language tasks, the bonus's weights, its losses),
declared and validated here once. A training run holds one as `TrainConfig.illm`; the options
`illm train --lambda-a`, `--beta-hc`, `--tasks`, ... are its fields. Its defaults are the `small`
preset's weights, the iLLM methods' default on the command line too (`illm_tools.intrinsic.presets`).

Kept apart from illm.py so that the command line reads it without importing torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from illm_tools.errors import UsageError
from illm_tools.intrinsic.presets import DEFAULT_SETTINGS
from illm_tools.settings import setting

SUMMARY_LOSSES = ("cosine", "mse")
ACTION_SIMILARITIES = ("tv", "bhattacharyya")


@dataclass
class ILLMConfig:
    """iLLM's settings: what its heads distil and how its bonus pays (see illm.py)."""

    RUN_FIELD: ClassVar[str] = "illm"
    """The `TrainConfig` field holding this config (`illm_tools.intrinsic.registry`: a run's own
    setting, not a `--bonus-option`)."""

    lambda_a: float = setting(DEFAULT_SETTINGS["lambda_a"], preset=True)
    """Weight lambda of the action-generation bonus r^a (paper: 0.8; the default is the `small`
    preset's, the paper's / 10)."""
    beta_hc: float = setting(DEFAULT_SETTINGS["beta_hc"], preset=True)
    """Weight beta of the history-compression bonus r^hc (paper: 0.5; the default is the `small`
    preset's, the paper's / 10)."""
    tasks: tuple[str, ...] = ("action", "summary")
    """The language tasks the heads distil and the bonus pays for, any combination of action,
    summary, goal and plan (paper Table 2; `illm_tools.tasks.registry`): each has its own head on
    the policy's features and its own bonus, weighted by lambda_a (action), beta_hc (summary) or
    `task_weights`. Methods with iLLM's heads only."""
    task_weights: dict = field(default_factory=dict)
    """Bonus weights of the tasks without a setting of their own by name (`--task-weight plan=0.3`);
    unset ones weigh 0.5, as beta_hc (their heads are trained like f^hc, paper D.2)."""
    summary_loss: str = "cosine"
    """Distillation loss of the text heads (f^hc and the goal/plan heads): cosine (1 - cos) or mse."""
    action_similarity: str = "tv"
    """Similarity behind r^a = 1 - sim: tv (1 - total variation) or bhattacharyya."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers
        from illm_tools.tasks.registry import get_task, parse_tasks

        check_numbers(self, non_negative=("lambda_a", "beta_hc"))
        if self.summary_loss not in SUMMARY_LOSSES:
            raise UsageError(f"summary_loss must be cosine or mse, got {self.summary_loss!r}")
        if self.action_similarity not in ACTION_SIMILARITIES:
            raise UsageError(f"action_similarity must be tv or bhattacharyya, got {self.action_similarity!r}")
        self.tasks = parse_tasks(self.tasks, "--tasks")
        self.task_weights = dict(self.task_weights or {})
        for name, weight in self.task_weights.items():
            if name not in self.tasks:
                raise UsageError(f"--task-weight {name}=...: {name} is not one of this run's --tasks "
                                 f"({','.join(self.tasks)})")
            if get_task(name).weight_setting is not None:
                raise UsageError(f"the {name} task's weight is --{get_task(name).weight_setting.replace('_', '-')}, "
                                 "not --task-weight")
            if not isinstance(weight, (int, float)) or weight < 0:
                raise UsageError(f"--task-weight {name}={weight!r}: a weight is a number >= 0")

    def weights(self) -> dict[str, float]:
        """Each task's bonus weight: lambda_a, beta_hc, or `task_weights` (default 0.5)."""
        from illm_tools.tasks.registry import DEFAULT_WEIGHT, get_task

        out = {}
        for task in self.tasks:
            setting = get_task(task).weight_setting
            out[task] = float(getattr(self, setting)) if setting else float(self.task_weights.get(task, DEFAULT_WEIGHT))
        return out

    def to_dict(self) -> dict:
        """JSON-ready form (the tasks as a list)."""
        return {"lambda_a": self.lambda_a, "beta_hc": self.beta_hc, "tasks": list(self.tasks),
                "task_weights": dict(self.task_weights), "summary_loss": self.summary_loss,
                "action_similarity": self.action_similarity}
