"""The interface every intrinsic bonus sits behind, and what the trainer hands it.

Owns `IntrinsicBonus` (the plug-in contract), `BonusContext` (what a bonus knows about the run
when it is built), `NoBonus` (plain PPO), `Targets` and the `TargetProvider` protocol (cache lookup
with live fallback, implemented in `illm_tools.rl.targets`; a bonus declares the kind it reads,
`target_kind`, and `illm_tools.rl.providers` maps the kind to its provider). Bonuses work on tensors only; they
never step environments. Methods (a name such as `rnd` -> a bonus class and its config) are
registered in `registry.py`. `StateRecord` and `HistoryTracker` (the per-step text state and the
per-env rolling history that builds it) live in `illm_tools.tasks.state`, shared with the annotate
stage, and are re-exported here.

The tensors a bonus may read (the trainer's side of the contract; every bonus gets all of them):

  images         [.., *obs shape]     the observation the policy acted from: the suite's policy
                                      array (`BonusContext.obs_kind` says which: MiniGrid's uint8
                                      (H, W, 3) symbolic view, Atari's (4, 84, 84) frames, ...)
  missions       int64 [.., L]        its mission as word ids (`Suite.mission_vocab`)
  actions        int64 [..]           the action taken
  ends           float [..]           1.0 where that transition ended its episode (terminated or
                                      truncated)
  next_images    [.., *obs shape]     the observation after the transition;
  next_missions  int64 [.., L]        ... and its mission. The pool resets in the same step (as
                                      gymnasium's SAME_STEP autoreset, and as CleanRL's
                                      ppo_rnd_envpool.py uses its next_obs), so where `ends` is 1
                                      this is the FIRST observation of the next episode, not the
                                      last one of the ended episode. For a rollout's last step it
                                      is the observation the next rollout starts from.
  features       float [.., F]        the policy network's torso features of `images`: as computed
                                      when acting (rollout, step), or with gradient (minibatch)

and, when the bonus's class declares them:

  needs_targets = True (LLM targets from the run's `TargetProvider`, e.g. an annotation cache):
  target_probs   float [.., A]        the LLM's distribution over the valid actions
  target_emb     float [.., K*D]      the LLM's text embeddings, one D-wide block per text task of
                                      the run (summary alone by default: K = 1)
  target_mask    bool  [..]           True where a target exists (other rows hold anything)
  (A method with `policy_heads` reads the run's language tasks, `TrainConfig.tasks`: action and
  summary by default, any combination of `illm_tools.tasks.registry`'s. Another method reads its
  `target_tasks`: ELLM's ("goal",) makes the run's provider a goal provider, whose targets carry
  only the mask, D = 0, and whose per-step goals the bonus reads from the provider itself, handed
  to it through `use_provider`.)
  policy_heads = True (the policy network carries iLLM's heads, one per language task, on its features):
  action_logits  float [.., A]        f^a's logits on `features` (with the action task)
  summary        float [.., K*D]      the text heads' predicted embeddings on `features` (f^hc's
                                      first with the summary task), blocks as in target_emb
  (both where `target_mask` is True; other rows hold anything: the heads need not run there)

The leading axes `..` are [N] for `observe` (one env step), [T, N] for `compute_rewards` and
`update` (one rollout, t-major), and [B] for `aux_loss` (one PPO minibatch of flat rows).

Hooks, in the order the trainer calls them per update: `observe` after every env step;
`compute_rewards` once after the rollout (reward t is paid with transition t, before the policy
update, and reaches the advantages through the intrinsic value stream); `aux_loss` on each
minibatch of the first `distill_epochs` epochs (its gradient reaches the policy network: iLLM's
distillation); `update` once after the policy update (a bonus's own model, own optimiser: RND's
predictor); `state_dict` / `load_state_dict` with every checkpoint; `use_provider` once, when the
trainer has built the bonus, with the run's `TargetProvider`: the one the run's assembly
(`illm_tools.rl.run`) built for the kind of targets the bonus declares (`target_kind`), for a bonus
that reads more of it than the stored targets.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch

from illm_tools.envs.observations import GridObservation, Observation
from illm_tools.tasks.state import StateRecord

__all__ = ["BonusContext", "BonusRewards", "IntrinsicBonus", "NoBonus", "StateRecord", "TargetProvider",
           "Targets"]


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


@dataclass(frozen=True)
class BonusContext:
    """What a bonus knows about the run when it is built (sizes of the tensors it will read)."""

    num_envs: int
    """N, the environments stepped side by side."""
    num_steps: int
    """T, the steps of one rollout per env."""
    image_shape: tuple[int, ...]
    """The shape of one observation (MiniGrid: (H, W, 3))."""
    num_actions: int
    """A, the valid actions."""
    feature_dim: int
    """F, the size of the policy's `features`."""
    int_gamma: float
    """Discount of the intrinsic value stream (a reward normaliser should use the same)."""
    seed: int
    """Seed of the bonus's own random streams (derived from the run's seed, apart from the
    trainer's; the trainer also seeds torch's global RNG with it while it builds the bonus)."""
    observation: Observation | None = None
    """How to read an observation (the suite's adapter, `illm_tools.envs.observations`); None: MiniGrid's
    grid of `image_shape`."""

    def __post_init__(self) -> None:
        if self.observation is None:
            from illm_tools.envs.suite import ObsSpec

            spec = ObsSpec(shape=tuple(self.image_shape), dtype="uint8", kind="grid", description="MiniGrid's grid")
            object.__setattr__(self, "observation", GridObservation(spec))

    @property
    def obs_kind(self) -> str:
        """The observation's kind (`ObsSpec.kind`)."""
        return self.observation.kind


class IntrinsicBonus(ABC):
    """One intrinsic bonus (see the module docstring for the tensors and the order of the hooks).

    A subclass sets `config_class` (a dataclass of its settings, built by the registry) and, when
    it needs them, `needs_targets` / `policy_heads`; it is built by `from_config(config, ctx)`.
    """

    config_class: ClassVar[type | None] = None
    """Dataclass of the bonus's settings (fields with defaults and docstrings); None: no settings.
    Its ClassVar `RUN_FIELD` names the TrainConfig field that holds it (its fields are then options
    of `illm train` of their own, e.g. iLLM's lambda_a in `TrainConfig.illm`) rather than bonus options."""
    needs_targets: ClassVar[bool] = False
    """The run must supply LLM targets (a `TargetProvider`); the batches then carry target_*."""
    policy_heads: ClassVar[bool] = False
    """The policy network carries the iLLM heads f^a / f^hc (trained by `aux_loss` through the
    policy's optimiser); the batches then carry action_logits and summary."""
    target_tasks: ClassVar[tuple[str, ...]] = ("action", "summary")
    """With `needs_targets` and without `policy_heads`: the language tasks (illm_tools.tasks.registry)
    whose cache rows the run's provider reads and the live fallback annotates (a method with the
    heads reads the run's `tasks`)."""
    target_kind: ClassVar[type] = TargetProvider
    """With `needs_targets`: the kind of targets the bonus reads, a `TargetProvider` protocol (this
    one: the targets of the run's language tasks; ELLM's `GoalProvider`: each state's suggested goals
    too). The bonus names no provider: whoever assembles the run builds the one registered for this
    kind (`illm_tools.rl.providers.TARGET_PROVIDERS`) and the trainer hands it to the bonus
    (`use_provider`); a plug-in declares a kind of its own and registers its provider there."""
    reads: ClassVar[tuple[str, ...] | None] = None
    """The rollout fields its batches need (of BONUS_FIELDS and the extras, illm_tools.rl.storage);
    None: all of them. The trainer gathers only these for each minibatch."""
    pays_reward: bool = True
    """Whether the rewards reach the advantages; False trains the bonus's models and pays nothing
    (e.g. `illm-noreward`, paper Table 3). Set by the registry entry, read by the trainer."""

    @classmethod
    def from_config(cls, config: Any, ctx: BonusContext) -> "IntrinsicBonus":
        """Build the bonus for a run (default: `cls(config, ctx)`)."""
        return cls(config, ctx)  # type: ignore[call-arg]

    def to(self, device: torch.device | str) -> "IntrinsicBonus":
        """Move the bonus's own models to `device`, where the trainer's tensors live (`--device`):
        every `torch.nn.Module` attribute, in place, so optimisers built on their parameters keep
        them. A bonus holding other tensors across rollouts moves them in an override. (Bonuses
        are not `nn.Module`s: most have no model, and their state is more than parameters.)"""
        for value in vars(self).values():
            if isinstance(value, torch.nn.Module):
                value.to(device)
            elif isinstance(value, IntrinsicBonus):  # a bonus inside another (NGU's RND)
                value.to(device)
        return self

    def use_provider(self, provider: TargetProvider) -> None:
        """Called once by the trainer, after it built the bonus, with the run's `TargetProvider` (the
        one registered for the bonus's `target_kind`, built by the run's assembly,
        `illm_tools.rl.run`), for a bonus that reads more of the provider than the targets the
        trainer stores (ELLM: each step's goals). Default: nothing."""

    def policy_outputs(self, net, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """What the bonus reads of the policy network beyond its features, for the batch's
        `features` [..., F] (the minibatch's, with gradient, during the update) and the rest of what
        it reads (`target_mask`, say): entries added to its batches. Default: nothing; iLLM's: its
        heads' outputs (`action_logits`, `summary`)."""
        return {}

    def observe(self, step: Mapping[str, torch.Tensor]) -> None:
        """Called after every env step with that step's [N, ...] tensors (default: nothing).
        For per-step state such as an episodic memory; must not change what the policy does."""

    @abstractmethod
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        """Intrinsic rewards [T, N] for a whole rollout (no gradient); updates normalisers."""

    def normalised(self, raw: torch.Tensor, norm, logs: dict[str, float]) -> BonusRewards:
        """The rollout's rewards of a bonus paid as `raw` divided by the running std of its
        discounted return (`norm`, a `DiscountedReturnNormalizer`): zeros when the method does not
        pay it (its models still train), else the normalised reward, with both logged."""
        if not self.pays_reward:
            return BonusRewards(torch.zeros_like(raw), logs)
        reward = norm(raw)
        logs.update(intrinsic_reward=float(reward.mean()), intrinsic_std=norm.rms.std)
        return BonusRewards(reward, logs)

    def aux_loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float | torch.Tensor]]:
        """Loss added to the PPO loss for one minibatch (default: none), and scalars to log: floats
        or 0-d tensors (the trainer averages them over the update and reads a GPU once per update)."""
        return torch.zeros(()), {}

    @property
    def uses_aux_loss(self) -> bool:
        """Whether this bonus overrides `aux_loss` (the trainer skips the call otherwise)."""
        return type(self).aux_loss is not IntrinsicBonus.aux_loss

    def update(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        """Train the bonus's own model with its own optimiser, once per rollout, after the policy
        update (default: nothing to train). Returns scalars to log."""
        return {}

    def state_dict(self) -> dict:
        """State to checkpoint (normalisers, own models, optimisers, random streams)."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what `state_dict` returned."""


class NoBonus(IntrinsicBonus):
    """Plain PPO: no reward, no loss, no state. Logs iLLM's two reward columns as 0, as plain PPO
    runs always have (metrics.csv keeps them filled for side-by-side reports)."""

    pays_reward = False

    def __init__(self, config: Any = None, ctx: BonusContext | None = None):
        pass

    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        t, n = batch["actions"].shape[:2]
        return BonusRewards(torch.zeros(t, n, device=batch["actions"].device),
                            {"intrinsic_reward_a": 0.0, "intrinsic_reward_hc": 0.0})
