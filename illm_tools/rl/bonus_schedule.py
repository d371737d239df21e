"""The weight of the intrinsic advantage over a run: constant, annealed, or gated by success.

`BonusSchedule` multiplies the run's `int_coef` each update (`TrainConfig.bonus_schedule`):
  constant  1 throughout (the paper's and RND's);
  anneal    1 - (update - 1) / updates: linear from 1 at the first update to 1/updates at the last,
            so the bonus steers early and the task late, whatever the level;
  success   1 - s, where s is a running success rate of the episodes that ended (an exponential
            moving average over updates with episodes, `SUCCESS_EMA` per update, starting at 0):
            the bonus pays while the level is unsolved and fades as it is solved, so it cannot go
            on pulling the agent away from a task it already solves (the weight adapts to the
            task's reward, not to a per-level constant).
The running rate is part of the checkpoint (a resumed run goes on with it). The success gate
needs a suite whose score is a success rate (`Suite.score_name`); the config refuses it elsewhere.
"""

from __future__ import annotations

import math

SCHEDULES = ("constant", "anneal", "success")
SUCCESS_EMA = 0.1
"""How much of the running success rate one update's episodes replace (a horizon of ~10 updates)."""


class BonusSchedule:
    """The factor on `int_coef` per update (see the module docstring)."""

    def __init__(self, kind: str, num_updates: int):
        if kind not in SCHEDULES:
            raise ValueError(f"bonus schedule must be one of {', '.join(SCHEDULES)}, got {kind!r}")
        self.kind, self.num_updates = kind, max(1, int(num_updates))
        self.success = 0.0

    def weight(self, update: int) -> float:
        """The factor for update `update` (1-based)."""
        if self.kind == "anneal":
            return max(0.0, 1.0 - (update - 1) / self.num_updates)
        if self.kind == "success":
            return max(0.0, 1.0 - self.success)
        return 1.0

    def observe(self, success_rate: float | None) -> None:
        """An update's success rate of the episodes that ended in it (None or NaN: none ended)."""
        if success_rate is None or math.isnan(success_rate):
            return
        self.success += SUCCESS_EMA * (float(success_rate) - self.success)

    def state_dict(self) -> dict:
        return {"kind": self.kind, "success": self.success}

    def load_state_dict(self, state: dict) -> None:
        self.success = float(state.get("success", 0.0))
