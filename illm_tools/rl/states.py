"""What a run tracks beside the policy, step by step: the LLM state of every step (its `StateRecord`,
the key of its targets) and what the network reads beside the observation, and the observers of the
steps (visit counts). The trainer talks to them through two small interfaces, so that it carries
no branch for iLLM(hop), iLLM(obs) or a suite's extras:

- a state source (`TextStates`, `NoStates`, hop's `illm_tools.hop.context.HopStates`): `current(obs)`
  -> (the records of the pool's current observations, the network's context [N, C] or None),
  `advance(obs, actions, ends, next_obs)` after each step; `context_dim` is C (0: none);
- a step observer (`VisitObserver`): `observe(obs)` with every new observation, `paid(reward)` with
  each rollout's intrinsic reward as paid ([T, N]; None where the run pays none), `state_dict` /
  `load_state_dict` (kept in the checkpoint under its `name`), `save(run_dir)` beside it.

`make_states` and `make_observers` pick them from the run's config and its first observations.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
import torch

from illm_tools.rl.config import TrainConfig
from illm_tools.tasks.state import HistoryTracker, StateRecord


class StateSource(Protocol):
    context_dim: int

    def current(self, obs) -> tuple[list[StateRecord], torch.Tensor | None]: ...

    def advance(self, obs, actions: Sequence[int], ends: Sequence[bool], next_obs) -> None: ...


class NoStates:
    """A run that needs no LLM state: no records, no context."""

    context_dim = 0

    def current(self, obs) -> tuple[list[StateRecord], None]:
        return [], None

    def advance(self, obs, actions, ends, next_obs) -> None:
        pass


class TextStates:
    """iLLM(obs), ELLM: each step's rendered text and mission with its episode's recent history."""

    context_dim = 0

    def __init__(self, num_envs: int, history_len: int, action_names: Sequence[str]):
        self.history = HistoryTracker(num_envs, history_len, action_names)

    def current(self, obs) -> tuple[list[StateRecord], None]:
        return self.history.records(obs.missions, obs.texts), None

    def advance(self, obs, actions, ends, next_obs) -> None:
        self.history.push(obs.texts, list(actions), list(ends))


def make_states(cfg: TrainConfig, suite, image_shape: tuple[int, ...], action_names: Sequence[str], *,
                needs_records: bool, device: torch.device | str = "cpu", num_envs: int | None = None) -> StateSource:
    """The run's state source: hop windows for `--mode hop` (their Z_h feeds the network whatever the
    method), the text history when the method reads LLM targets, else none."""
    if cfg.setup.obs_mode != "hop":
        return TextStates(num_envs or cfg.num_envs, cfg.setup.history_len, action_names) if needs_records else NoStates()
    from illm_tools.hop.context import HopStates

    return HopStates(cfg, suite, image_shape, action_names, device, num_envs)


class VisitObserver:
    """Per-cell visit counts where the env reports the agent's position (`info["agent_pos"]`: MiniGrid,
    paper Figure 1), saved as `visitation.npy` with each checkpoint; and where the bonus was paid
    (`paid`: each step's intrinsic reward added at the cell the agent acted from), `bonus_visitation.npy`."""

    name = "visits"

    def __init__(self, first_obs):
        from illm_tools.rl.visitation import VisitCounts

        self.counts = VisitCounts()
        self.bonus = VisitCounts(weighted=True)
        self.counts.add(first_obs.positions)
        self._current = np.asarray(first_obs.positions)
        self._acted: list[np.ndarray] = []  # this rollout's positions acted from, one [N, 2] per step

    def observe(self, obs) -> None:
        self.counts.add(obs.positions)
        self._acted.append(self._current)
        self._current = np.asarray(obs.positions)

    def paid(self, reward) -> None:
        """The rollout's intrinsic reward paid, [T, N] (t-major), each at the cell its step acted from
        (None: the run pays none; the rollout's positions are dropped)."""
        steps = self._acted[-len(reward):] if reward is not None else []
        if steps:
            self.bonus.add(np.stack(steps), np.asarray(reward, dtype=np.float64)[-len(steps):])
        self._acted.clear()

    def state_dict(self) -> dict:
        return {**self.counts.state_dict(), "bonus": self.bonus.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.counts.load_state_dict(state)
        if "bonus" in state:  # a checkpoint from before the bonus map: it starts empty
            self.bonus.load_state_dict(state["bonus"])

    def save(self, run_dir) -> None:
        from illm_tools.rl.visitation import BONUS_FILE

        self.counts.save(run_dir)
        if self.bonus.counts.size:
            self.bonus.save(run_dir, BONUS_FILE)


def make_observers(first_obs) -> list:
    """The step observers a pool's observations allow (visit counts where it reports positions)."""
    return [VisitObserver(first_obs)] if getattr(first_obs, "positions", None) is not None else []
