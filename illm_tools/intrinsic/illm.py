"""The iLLM bonus: distil the LLM into the heads f^a / f^hc and pay where they still disagree.

Methods `illm` and `illm-noreward` (registry.py). Declares `needs_targets` (the run supplies LLM
targets) and `policy_heads` (the policy network carries f^a / f^hc, trained through `aux_loss`).
Settings: `ILLMConfig`, whose fields are the run's own (TrainConfig) settings of the same names.

Reads (rewards: [T, N, ...]; loss: [B, ...]; see base.py):
  action_logits  f^a's logits over the valid actions      [.., A]
  summary        f^hc's predicted summary embedding        [.., D]
  target_probs   the LLM's distribution over valid actions [.., A]
  target_emb     the LLM's summary embedding               [.., D]
  target_mask    bool, True where the LLM target exists    [..]

Choices (documented here once):
- Action distillation loss: KL(p_LLM || softmax(f^a)). Same gradient as cross-entropy, but 0 at
  a perfect match, so the logged value reads as remaining disagreement.
- Summary distillation loss: 1 - cos(f^hc, target) by default (scale-free, the same quantity
  r^hc pays), or MSE.
- r^a = 1 - sim(softmax(f^a), p_LLM) with sim = 1 - total variation (so r^a is the TV distance,
  in [0, 1]) or the Bhattacharyya coefficient (r^a is then the squared Hellinger distance).
- r^hc = clip(1 - cos(f^hc, target), 0, 1).
- Both are zero where there is no target (and those steps are counted), each is divided by the
  running std of its own discounted return (normalize.py), and the bonus paid is
  lambda * r^a + beta * r^hc. The trainer feeds it to a separate intrinsic value head (RND's
  two streams); with unit advantage weights this is PPO on r* = r + lambda r^a + beta r^hc.
- The rewards of a rollout are paid for the state the agent acts from (paper Alg. 1, line 11):
  reward t belongs to state s_t, computed after the rollout from the updated heads in one batch.

Compared with CleanRL's RND (`cleanrl/ppo_rnd_envpool.py`), the reference most users know:
- Same: the reward is divided by sqrt(var) of a RunningMeanStd of the discounted intrinsic
  return R = r + gamma R (int_gamma 0.99), per-env filter never reset at episode ends, moments of
  all T x N values merged once per rollout, mean not subtracted; the intrinsic stream is
  non-episodic (int_nextnonterminal = 1; our int_episodic=False); the two advantages are summed
  with weights and then normalised per minibatch, so only their ratio matters (logged per update as
  charts/adv_int_ext_ratio, with charts/adv_ext_abs, adv_int_abs, return_ext, return_int).
- CleanRL filters over the wrong axis: it iterates over `curiosity_rewards.T` ([N, T]), so its
  "return" accumulates across envs at each time step (cleanrl issue #360); we, like the original
  openai/random-network-distillation code, accumulate over time per env. Its std differs from ours.
- Weights: RND uses ext_coef 2, int_coef 1 (and gamma 0.999); we default to 1, 1, i.e. PPO on
  r* = r + lambda r^a + beta r^hc as the paper writes it (`illm train --bonus-preset rnd` for 2, 1).
- RND pays every step; here steps without an LLM target pay 0 and are left out of the variance,
  so at low coverage the std is that of the covered steps' returns. r^a and r^hc are normalised
  separately, then weighted by lambda and beta; RND has one bonus. We add 1e-8 to the std.
- CleanRL never clips the intrinsic value loss; the trainer clips both (clip_vloss). RND pays the
  reward of transition t for s_{t+1} (its prediction error on next_obs); we pay it for s_t.
- Scale: the normaliser fixes the spread of R, not the reward's level. A bonus that is nearly
  constant (as with small LLMs' near state-independent rankings) has a large R with a small spread,
  so its normalised reward grows as the running variance settles; V_int absorbs the constant part,
  and the ratio metric shows how much of the summed advantage the bonus still is.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F

from illm_tools.errors import UsageError
from illm_tools.intrinsic.base import BonusContext, BonusRewards, IntrinsicBonus
from illm_tools.intrinsic.normalize import DiscountedReturnNormalizer


@dataclass
class ILLMConfig:
    """iLLM's settings. Each is the training run's setting of the same name (`TrainConfig`,
    `illm train --lambda-a` etc.), so they are not bonus options."""

    RUN_SETTINGS: ClassVar[tuple[str, ...]] = ("lambda_a", "beta_hc", "summary_loss", "action_similarity")

    lambda_a: float = 0.8
    """Weight lambda of the action-generation bonus r^a (paper: 0.8)."""
    beta_hc: float = 0.5
    """Weight beta of the history-compression bonus r^hc (paper: 0.5)."""
    summary_loss: str = "cosine"
    """Distillation loss of f^hc: cosine (1 - cos) or mse."""
    action_similarity: str = "tv"
    """Similarity behind r^a = 1 - sim: tv (1 - total variation) or bhattacharyya."""

    def __post_init__(self) -> None:
        if self.summary_loss not in ("cosine", "mse"):
            raise UsageError(f"summary_loss must be cosine or mse, got {self.summary_loss!r}")
        if self.action_similarity not in ("tv", "bhattacharyya"):
            raise UsageError(f"action_similarity must be tv or bhattacharyya, got {self.action_similarity!r}")


def action_disagreement(logits: torch.Tensor, target: torch.Tensor, kind: str = "tv") -> torch.Tensor:
    """1 - similarity of softmax(logits) and target along the last axis, in [0, 1]."""
    q = logits.softmax(-1)
    if kind == "tv":
        return (0.5 * (q - target).abs().sum(-1)).clamp(0.0, 1.0)
    if kind == "bhattacharyya":
        return (1.0 - (q * target.clamp_min(0.0)).sqrt().sum(-1)).clamp(0.0, 1.0)
    raise ValueError(f"unknown action similarity {kind!r}")


def summary_disagreement(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """clip(1 - cos(pred, target), 0, 1) along the last axis."""
    return (1.0 - F.cosine_similarity(pred, target, dim=-1, eps=1e-8)).clamp(0.0, 1.0)


def _clean(batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mask and targets with rows that have no target zeroed (they may hold NaN or garbage)."""
    mask = batch["target_mask"].bool()
    m = mask.unsqueeze(-1)
    probs, emb = batch["target_probs"], batch["target_emb"]
    return mask, torch.where(m, probs, torch.zeros_like(probs)), torch.where(m, emb, torch.zeros_like(emb))


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp_min(1.0)


class ILLMBonus(IntrinsicBonus):
    """iLLM's two bonuses and distillation losses (see the module docstring)."""

    config_class = ILLMConfig
    needs_targets = True
    policy_heads = True

    def __init__(self, num_envs: int, *, lambda_a: float = 0.8, beta_hc: float = 0.5,
                 gamma: float = 0.99, pays_reward: bool = True, summary_loss: str = "cosine",
                 action_similarity: str = "tv"):
        self.lambda_a = lambda_a
        self.beta_hc = beta_hc
        self.pays_reward = pays_reward
        self.summary_loss = summary_loss
        self.action_similarity = action_similarity
        self.norm_a = DiscountedReturnNormalizer(num_envs, gamma)
        self.norm_hc = DiscountedReturnNormalizer(num_envs, gamma)

    @classmethod
    def from_config(cls, config: ILLMConfig, ctx: BonusContext) -> "ILLMBonus":
        return cls(ctx.num_envs, lambda_a=config.lambda_a, beta_hc=config.beta_hc, gamma=ctx.int_gamma,
                   summary_loss=config.summary_loss, action_similarity=config.action_similarity)

    @torch.no_grad()
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        mask, probs, emb = _clean(batch)
        r_a = action_disagreement(batch["action_logits"], probs, self.action_similarity)
        r_hc = summary_disagreement(batch["summary"], emb)
        r_a = torch.where(mask, r_a, torch.zeros_like(r_a))
        r_hc = torch.where(mask, r_hc, torch.zeros_like(r_hc))
        logs = {
            "intrinsic_reward_a": float(_masked_mean(r_a, mask)),
            "intrinsic_reward_hc": float(_masked_mean(r_hc, mask)),
            "target_coverage": float(mask.float().mean()),
            "no_target_steps": float((~mask).sum()),
        }
        if not self.pays_reward:
            return BonusRewards(torch.zeros_like(r_a), logs)
        reward = self.lambda_a * self.norm_a(r_a, mask) + self.beta_hc * self.norm_hc(r_hc, mask)
        logs["intrinsic_reward"] = float(reward.mean())
        logs["intrinsic_std_a"] = self.norm_a.rms.std
        logs["intrinsic_std_hc"] = self.norm_hc.rms.std
        return BonusRewards(reward, logs)

    def aux_loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        """Masked mean of the two distillation losses, summed (gradients reach heads and torso)."""
        mask, target, emb = _clean(batch)
        kl = (torch.xlogy(target, target) - target * batch["action_logits"].log_softmax(-1)).sum(-1)
        pred = batch["summary"]
        if self.summary_loss == "cosine":
            hc = 1.0 - F.cosine_similarity(pred, emb, dim=-1, eps=1e-8)
        else:
            hc = (pred - emb).pow(2).mean(-1)
        kl = torch.where(mask, kl, torch.zeros_like(kl))
        hc = torch.where(mask, hc, torch.zeros_like(hc))
        loss_a, loss_hc = _masked_mean(kl, mask), _masked_mean(hc, mask)
        return loss_a + loss_hc, {"distill_action": loss_a.item(), "distill_summary": loss_hc.item()}

    def state_dict(self) -> dict:
        return {"norm_a": self.norm_a.state_dict(), "norm_hc": self.norm_hc.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.norm_a.load_state_dict(state["norm_a"])
        self.norm_hc.load_state_dict(state["norm_hc"])
