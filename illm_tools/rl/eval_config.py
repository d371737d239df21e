"""EvalConfig: the settings of an `illm eval` (its options are the fields, as TrainConfig's are)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from illm_tools.errors import UsageError


@dataclass
class EvalConfig:
    """An `illm eval`: which trained runs, on how many fresh episodes, acting how."""

    runs: tuple[Path, ...]
    """Run folders written by `illm train` (several give a table)."""
    episodes: int = 100
    """Episodes to play per run."""
    seed: int = 0
    """Evaluation seed (episodes are disjoint from training seeds)."""
    greedy: bool = False
    """Take the most likely action instead of sampling."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        self.runs = tuple(Path(r) for r in self.runs)
        check_numbers(self, positive=("episodes",), non_negative=("seed",))
        missing = [str(r) for r in self.runs if not (r / "config.json").is_file()]
        if missing or not self.runs:
            raise UsageError(f"no training run at {', '.join(missing[:3]) or '(none given)'}: pass folders written "
                             "by `illm train`")
