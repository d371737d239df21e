"""ELLM (Du, Watkins, Wang, Colas, Darrell, Abbeel, Gupta and Andreas, "Guiding Pretraining in
Reinforcement Learning with Large Language Models", ICML 2023; code github.com/yuqingd/ellm): pay
the agent for transitions that achieve a goal the LLM suggested for the state it acted from.

Method `ellm` (registry.py); settings `ELLMConfig` (`illm train --method ellm --bonus-option
KEY=VALUE`). Declares `needs_targets` with `target_tasks = ("goal",)` and `target_kind =
GoalProvider`: the run's provider is the one registered for that kind
(`illm_tools.rl.providers`), `illm_tools.rl.targets.GoalTargets`, which reads each state's goals from the annotation cache
(`illm annotate --tasks goal`: the paper's Appendix D.2 goal prompt, generated greedily and parsed
into a list, `illm_tools.tasks.goals.parse_goals`) with the same keys and live fallback as iLLM's
targets. Reads `images`, `actions`, `next_images`, `ends` and `target_mask` (see base.py), and the
provider's per-step goals, handed to the bonus with `use_provider`; no policy heads.

The reward of transition t (o_t, a_t, o_{t+1}) of env i, ELLM's R_int (paper Sec. 3; the code's
`CrafterLMGoalWrapper.text_reward`):
- caption c_t = the BabyAI captioner's sentence for the transition (`illm_tools.envs.captions`,
  e.g. "you picked up the red ball"); goals g_1..g_k = the goals suggested for state s_t;
- embeddings E[.] from all-MiniLM-L6-v2 (`illm_tools.llm.sentence`; ELLM's code uses
  SentenceBERT's paraphrase-MiniLM-L3-v2, this project ships L6), unit vectors;
- Delta_j = cos(E[c_t], E[g_j]); r_t = max_j Delta_j if it is above `threshold` (default 0.83, by
  the measurement below; ELLM's own is 0.99, `env_spec.threshold` in its config.yaml: "cosine
  similarity threshold above which a goal is considered achieved"), else 0; the similarity
  itself is paid, as in ELLM;
- novelty (ELLM's `novelty_bonus: True`, "only reward for each goal once"): every goal whose
  similarity passes the threshold counts as achieved for the rest of env i's episode and is not
  paid again in it, in this state or any other that suggests the same goal (goals compared as the
  parsed, lower-cased strings); the set is cleared when the episode ends;
- no reward where the state has no goal row (counted: `target_coverage`, `no_target_steps`, as
  iLLM counts its targets), where its row holds no goal (`goal_empty_steps`), or where the caption
  is "you did nothing" (ELLM's own check: such steps are never compared).

Choices: the reward is scaled by `coef` and, with `normalize` on, divided by the running std of
its discounted return like iLLM's and RND's (off by default: ELLM adds its raw similarity).
Captions of an episode's last transition come from the view before it (the pool has already
reset the env; `illm_tools.envs.captions` predicts the effect). The per-env sets of achieved goals
are not checkpointed: a resumed run restarts its environments.

Measured with all-MiniLM-L6-v2: a caption scores 0.84-0.87 against the goal it fulfils in the
imperative ("you picked up the red ball" / "pick up the red ball": 0.86) and up to 0.81 against a
near miss ("you dropped the blue key" / "pick up the blue key"), so ELLM's 0.99 would pay only goals
the LLM worded almost as the caption: the default 0.83 sits between the two
(`--bonus-option threshold=0.99` is ELLM's setting).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np
import torch

from illm_tools.errors import UsageError
from illm_tools.intrinsic.base import BonusContext, BonusRewards, IntrinsicBonus, TargetProvider
from illm_tools.intrinsic.normalize import DiscountedReturnNormalizer


@runtime_checkable
class GoalProvider(TargetProvider, Protocol):
    """The targets ELLM reads (its `target_kind`): a `TargetProvider` whose `goals`, after each
    `targets` call, hold each record's suggested goals (a tuple, possibly empty), None where the
    state has no goal row; its `targets` carry only the mask."""

    goals: list[tuple[str, ...] | None]


@dataclass
class ELLMConfig:
    """ELLM's settings (`--bonus-option KEY=VALUE`)."""

    threshold: float = 0.83
    """Cosine similarity above which a goal counts as achieved and is paid (ELLM's config.yaml: 0.99)."""
    coef: float = 1.0
    """Weight of the reward (ELLM adds the similarity as it is: 1)."""
    normalize: bool = False
    """Divide the reward by the running std of its discounted return (as iLLM and RND do)."""

    def __post_init__(self) -> None:
        if not -1.0 <= self.threshold < 1.0:
            raise UsageError(f"ELLM's threshold must lie in [-1, 1), got {self.threshold}")
        if self.coef <= 0:
            raise UsageError(f"ELLM's coef must be positive, got {self.coef}")


class ELLMBonus(IntrinsicBonus):
    """ELLM's goal-achievement reward (see the module docstring). `embedder` (anything with
    `encode(texts) -> float32 [n, d]` unit vectors) defaults to all-MiniLM-L6-v2, loaded on the
    first rollout; tests pass a small one."""

    config_class = ELLMConfig
    needs_targets = True
    target_tasks: ClassVar[tuple[str, ...]] = ("goal",)
    target_kind: ClassVar[type] = GoalProvider

    def __init__(self, config: ELLMConfig, ctx: BonusContext, embedder=None):
        from illm_tools.envs.captions import captioner

        if ctx.obs_kind != "grid":
            raise UsageError(f"--method ellm captions MiniGrid transitions (what the agent picked up, opened, reached); "
                             f"it has no captioner for {ctx.obs_kind} observations: use it on BabyAI/MiniGrid")
        self.config = config
        self.num_envs = ctx.num_envs
        self.embedder = embedder
        self.provider: TargetProvider | None = None
        self.captioner = captioner()
        self.achieved: list[set[str]] = [set() for _ in range(ctx.num_envs)]
        """Per env, the goals achieved so far in its current episode (not paid again in it)."""
        self.norm = DiscountedReturnNormalizer(ctx.num_envs, ctx.int_gamma)

    def use_provider(self, provider: TargetProvider) -> None:
        if not hasattr(provider, "goals"):
            raise UsageError(f"--method ellm reads suggested goals; the run's target provider "
                             f"{type(provider).__name__} has none (use illm_tools.rl.targets.GoalTargets)")
        self.provider = provider

    def _embed(self, texts: list[str]) -> dict[str, np.ndarray]:
        if self.embedder is None:
            from illm_tools.llm.sentence import shared_embedder

            self.embedder = shared_embedder()
        unique = list(dict.fromkeys(texts))
        return dict(zip(unique, self.embedder.encode(unique))) if unique else {}

    @torch.no_grad()
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        from illm_tools.envs.captions import NOTHING, caption_transitions

        if self.provider is None:
            raise UsageError("the ELLM bonus has no goal provider: build the run with illm_tools.rl.run.train, "
                             "or call bonus.use_provider(GoalTargets(...)) after building the Trainer")
        t, n = batch["actions"].shape[:2]
        goals = self.provider.goals  # type: ignore[attr-defined]
        if len(goals) != t * n:
            raise UsageError(f"the goal provider holds {len(goals)} steps' goals; this rollout has {t * n}")
        device = batch["actions"].device
        ends = batch["ends"].reshape(-1).bool().cpu().numpy()
        captions = caption_transitions(batch["images"].reshape(t * n, *batch["images"].shape[2:]).cpu().numpy(),
                                       batch["actions"].reshape(-1).tolist(),
                                       batch["next_images"].reshape(t * n, *batch["next_images"].shape[2:]).cpu().numpy(),
                                       ends)
        mask = batch["target_mask"].reshape(-1).bool().cpu().numpy() & np.array([g is not None for g in goals])
        compared = [k for k in range(t * n) if mask[k] and goals[k] and captions[k] != NOTHING]
        vectors = self._embed([captions[k] for k in compared] + [g for k in compared for g in goals[k]])
        reward = np.zeros(t * n, np.float32)
        paid_goals = 0
        todo = set(compared)
        for k in range(t * n):  # t-major: each env's steps in time order
            i = k % n
            if k in todo:
                left = [g for g in goals[k] if g not in self.achieved[i]]
                if left:
                    sims = np.stack([vectors[g] for g in left]) @ vectors[captions[k]]
                    hit = sims > self.config.threshold
                    if hit.any():
                        reward[k] = float(sims.max())
                        self.achieved[i].update(g for g, h in zip(left, hit) if h)
                        paid_goals += int(hit.sum())
            if ends[k]:
                self.achieved[i].clear()
        r = torch.as_tensor(reward, device=device).view(t, n)
        m = torch.as_tensor(mask, device=device).view(t, n)
        covered = max(int(mask.sum()), 1)
        logs = {
            "intrinsic_reward_ellm": float(r.sum()) / covered,
            "ellm_paid_steps": float((reward > 0).sum()),
            "ellm_goals_achieved": float(paid_goals),
            "target_coverage": float(mask.mean()),
            "no_target_steps": float((~mask).sum()),
            "goal_empty_steps": float(sum(1 for k in range(t * n) if mask[k] and not goals[k])),
        }
        if not self.pays_reward:
            return BonusRewards(torch.zeros_like(r), logs)
        paid = self.norm(r, m) if self.config.normalize else r
        paid = self.config.coef * paid
        logs["intrinsic_reward"] = float(paid.mean())
        return BonusRewards(paid, logs)

    def state_dict(self) -> dict:
        return {"captioner": self.captioner, "norm": self.norm.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.norm.load_state_dict(state["norm"])
