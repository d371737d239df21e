"""The interface every intrinsic bonus sits behind, and what the trainer hands an LLM target source.

Owns: `Targets` and the `TargetProvider` protocol (cache lookup with live fallback, implemented
in `illm_tools.rl.targets`), and `IntrinsicBonus`, the small rllte-style interface (compute
rewards for a rollout, auxiliary loss, update, state for checkpoints). Bonuses work on tensors
only; they never step environments. `StateRecord` and `HistoryTracker` (the per-step text state
and the per-env rolling history that builds it) live in `illm_tools.tasks.state`, shared with the
annotate stage, and are re-exported here.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch

from illm_tools.tasks.state import StateRecord

__all__ = ["BonusRewards", "IntrinsicBonus", "StateRecord", "TargetProvider", "Targets"]


class Targets(NamedTuple):
    """LLM targets for a batch of B states; unpacks as (action_probs, embeddings, mask).

    action_probs float32 [B, A] (the LLM's distribution over the valid actions; rows sum to 1
    where mask is True), embeddings float32 [B, D] (summary embedding), mask bool [B] (True where
    a target exists; other rows are ignored and may hold anything).
    """

    action_probs: np.ndarray
    embeddings: np.ndarray
    mask: np.ndarray


@runtime_checkable
class TargetProvider(Protocol):
    """Source of LLM targets, called once per rollout with every step's record.

    `stats()` returns running counters the trainer logs; it reads `cache_hit_rate` (fraction of
    looked-up states found in the cache) and `live_annotations` (states annotated by the live LLM
    so far), and ignores other keys.
    """

    def targets(self, records: Sequence[StateRecord]) -> Targets: ...

    def stats(self) -> Mapping[str, float]: ...


@dataclass
class BonusRewards:
    """What a bonus returns for a rollout: the reward paid ([T, N], already weighted and
    normalised; zeros when the bonus does not pay) and scalars to log."""

    reward: torch.Tensor
    logs: dict[str, float]


class IntrinsicBonus(ABC):
    """One intrinsic bonus. `batch` maps documented names to [T, N, ...] (rewards) or [B, ...]
    (loss) tensors; each bonus's docstring lists the names it reads."""

    pays_reward: bool = True

    @abstractmethod
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        """Intrinsic rewards for a whole rollout (no gradient); updates normalisers."""

    def aux_loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        """Loss added to the PPO loss for one minibatch (default: none)."""
        return torch.zeros(()), {}

    def update(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        """Train a bonus's own model with its own optimiser (default: nothing to train)."""
        return {}

    def state_dict(self) -> dict:
        """State to checkpoint (normalisers, own models)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what `state_dict` returned."""
