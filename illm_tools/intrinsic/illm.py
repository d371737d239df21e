"""The iLLM bonus: distil the LLM into the heads f^a / f^hc and pay where they still disagree.

Methods `illm` and `illm-noreward` (registry.py). Declares `needs_targets` (the run supplies LLM
targets) and `policy_heads` (the policy network carries f^a / f^hc, trained through `aux_loss`).
Settings: `ILLMConfig` (illm_config.py), a training run's `TrainConfig.illm`.

Reads (rewards: [T, N, ...]; loss: [B, ...]; see base.py):
  action_logits  f^a's logits over the valid actions      [.., A]
  summary        the text heads' predicted embeddings      [.., K*D]
  target_probs   the LLM's distribution over valid actions [.., A]
  target_emb     the LLM's text embeddings                 [.., K*D]
  target_mask    bool, True where the LLM target exists    [..]

The language tasks are the run's `tasks` (paper Table 2; default action + summary, the paper's
two): the action task on f^a, and K text tasks (summary on f^hc, goal, plan), each on its own
head, their D-wide blocks side by side in task order. Every task below has its own distillation
loss, bonus and normaliser; the goal and plan heads are trained and paid as f^hc is (paper D.2),
weighted by `task_weights` (default 0.5, beta's value).

Choices (documented here once):
- Action distillation loss: KL(p_LLM || softmax(f^a)). Same gradient as cross-entropy, but 0 at
  a perfect match, so the logged value reads as remaining disagreement.
- Summary distillation loss: 1 - cos(f^hc, target) by default (scale-free, the same quantity
  r^hc pays), or MSE.
- r^a = 1 - sim(softmax(f^a), p_LLM) with sim = 1 - total variation (so r^a is the TV distance,
  in [0, 1]) or the Bhattacharyya coefficient (r^a is then the squared Hellinger distance).
- r^hc = clip(1 - cos(f^hc, target), 0, 1).
- All are zero where there is no target (a step has one when the cache answers every task of the
  run; those without are counted), each is divided by the running std of its own discounted
  return (normalize.py), and the bonus paid is b = lambda * r^a + beta * r^hc (+ w_goal * r^goal +
  w_plan * r^plan with those tasks). By default (`reward_streams` 2) the trainer feeds b to a second
  critic, the intrinsic value head, with its own non-episodic return (RND's two streams), and sums
  the two advantages weighted by ext_coef and int_coef. That is not PPO on r* = r + lambda r^a +
  beta r^hc, even with unit weights: a second critic, and an intrinsic return that runs on across
  episode ends, differ from one critic of the summed reward. `--reward-streams 1` is that one-stream
  form (the paper's Algorithm 1).
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
- Weights: RND uses ext_coef 2, int_coef 1 (and gamma 0.999); we default to 1, 1, the paper's
  unit weights on r and the bonus, in two streams (`illm train --bonus-preset rnd` for 2, 1).
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

import torch

from illm_tools.intrinsic.base import BonusContext, BonusRewards, IntrinsicBonus
from illm_tools.intrinsic.illm_config import ILLMConfig
from illm_tools.intrinsic.normalize import DiscountedReturnNormalizer
from illm_tools.tasks.registry import text_tasks


def action_disagreement(logits: torch.Tensor, target: torch.Tensor, kind: str = "tv") -> torch.Tensor:
    """1 - similarity of softmax(logits) and target along the last axis, in [0, 1]."""
    q = logits.softmax(-1)
    if kind == "tv":
        return (0.5 * (q - target).abs().sum(-1)).clamp(0.0, 1.0)
    if kind == "bhattacharyya":
        return (1.0 - (q * target.clamp_min(0.0)).sqrt().sum(-1)).clamp(0.0, 1.0)
    raise ValueError(f"unknown action similarity {kind!r}")


def cosine(pred: torch.Tensor, target: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """cos(pred, target) along the last axis, as `F.cosine_similarity(pred, target, eps=eps)`
    computes it (each norm clamped at `eps`), with the target (a constant: no gradient) normalised
    first: its backward is a third of `cosine_similarity`'s on a CPU (1.49 against 0.48 ms for
    512 x 576), and the heads' loss takes it every minibatch."""
    unit = target / torch.linalg.vector_norm(target, dim=-1, keepdim=True).clamp_min(eps)
    return torch.linalg.vecdot(pred, unit) / torch.linalg.vector_norm(pred, dim=-1).clamp_min(eps)


def summary_disagreement(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """clip(1 - cos(pred, target), 0, 1) along the last axis."""
    return (1.0 - cosine(pred, target)).clamp(0.0, 1.0)


def _clean(batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mask and targets with rows that have no target zeroed (they may hold NaN or garbage). With
    every row covered on a CPU (a cached run) the targets are returned as they are, which is what
    zeroing none of them gives: the copy of the embeddings was 0.57 ms of a bonus pass (2,048 x 576)."""
    mask = batch["target_mask"].bool()
    probs, emb = batch["target_probs"], batch["target_emb"]
    if mask.device.type == "cpu" and bool(mask.all()):  # on CUDA the test would wait for the device
        return mask, probs, emb
    m = mask.unsqueeze(-1)
    return mask, torch.where(m, probs, 0.0), torch.where(m, emb, 0.0)


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(x.dtype)
    return (x * m).sum() / m.sum().clamp_min(1.0)


_SUFFIX = {"action": "a", "summary": "hc"}
"""The paper's names of the first two tasks' columns (intrinsic_reward_a, intrinsic_reward_hc)."""


def _suffix(task: str) -> str:
    return _SUFFIX.get(task, task)


class ILLMBonus(IntrinsicBonus):
    """iLLM's bonuses and distillation losses, one per language task of the run (see the module
    docstring): the action task's on f^a, each text task's on its own head, whose predictions
    arrive side by side in `summary` (and the targets in `target_emb`), D each, in task order."""

    config_class = ILLMConfig
    needs_targets = True
    policy_heads = True
    reads = ("features", "target_probs", "target_emb", "target_mask")

    def __init__(self, num_envs: int, *, gamma: float = 0.99, pays_reward: bool = True,
                 config: ILLMConfig | None = None, **settings):
        """`config`, or one made of `settings` (ILLMConfig's fields: lambda_a, beta_hc, tasks, ...),
        whose defaults are ILLMConfig's."""
        config = config if config is not None else ILLMConfig(**settings)
        self.config = config
        self.lambda_a, self.beta_hc = config.lambda_a, config.beta_hc
        self.pays_reward = pays_reward
        self.summary_loss = config.summary_loss
        self.action_similarity = config.action_similarity
        self.tasks = config.tasks
        self.text = text_tasks(self.tasks)
        self.weights = config.weights()
        self.norms = {task: DiscountedReturnNormalizer(num_envs, gamma) for task in self.tasks}

    @property
    def norm_a(self) -> DiscountedReturnNormalizer:
        return self.norms["action"]

    @property
    def norm_hc(self) -> DiscountedReturnNormalizer:
        return self.norms["summary"]

    @classmethod
    def from_config(cls, config: ILLMConfig, ctx: BonusContext) -> "ILLMBonus":
        return cls(ctx.num_envs, gamma=ctx.int_gamma, config=config)

    def _text_blocks(self, pred: torch.Tensor, emb: torch.Tensor) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
        """Each text task's (prediction, target) block of the side-by-side [.., K * D] tensors."""
        if not self.text:
            return {}
        d = emb.shape[-1] // len(self.text)
        return {task: (pred[..., i * d:(i + 1) * d], emb[..., i * d:(i + 1) * d]) for i, task in enumerate(self.text)}

    def policy_outputs(self, net, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The heads' outputs on `batch["features"]` [..., F]: `action_logits` (f^a) and `summary` (f^hc
        and the other text tasks' heads, side by side), shaped as the features' leading dimensions.
        A step without a target takes no part in the bonus or the loss, so on a CPU the heads run on
        the steps with one only, and the others hold zeros (an async run's first rollouts: about 1% of
        the steps have one, and the heads on the rest were most of the update). Every row has one
        with a full cache, and on CUDA (where picking the rows would wait for the device) the heads
        run on every row."""
        features = batch["features"]
        flat = features.reshape(-1, features.shape[-1])
        mask = batch["target_mask"].reshape(-1)
        if flat.device.type == "cpu" and not bool(mask.all()):
            rows = mask.nonzero().squeeze(1)
            outputs = [None if out is None else out.new_zeros(len(flat), out.shape[1]).index_copy(0, rows, out)
                       for out in net.heads(flat[rows])]  # none: the heads still get (zero) gradients, as before
        else:
            outputs = net.heads(flat)
        return {name: out.reshape(*features.shape[:-1], -1)
                for name, out in zip(("action_logits", "summary"), outputs) if out is not None}

    @torch.no_grad()
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        mask, probs, emb = _clean(batch)
        raw = {}
        if "action" in self.tasks:
            raw["action"] = action_disagreement(batch["action_logits"], probs, self.action_similarity)
        for task, (pred, target) in self._text_blocks(batch["summary"], emb).items():
            raw[task] = summary_disagreement(pred, target)
        raw = {task: torch.where(mask, r, 0.0) for task, r in raw.items()}
        logs = {f"intrinsic_reward_{_suffix(t)}": float(_masked_mean(r, mask)) for t, r in raw.items()}
        logs.update(target_coverage=float(mask.float().mean()), no_target_steps=float((~mask).sum()))
        if "action" in self.tasks:  # how much of the annotator f^a has learned: its best action = the annotator's
            agree = batch["action_logits"].argmax(-1) == probs.argmax(-1)
            logs["head_agreement"] = float(_masked_mean(agree.float(), mask))
        if not self.pays_reward:
            return BonusRewards(torch.zeros_like(mask, dtype=torch.float32), logs)
        reward = sum(self.weights[t] * self.norms[t](r, mask) for t, r in raw.items())
        logs["intrinsic_reward"] = float(reward.mean())
        logs.update({f"intrinsic_std_{_suffix(t)}": self.norms[t].rms.std for t in raw})
        return BonusRewards(reward, logs)

    def aux_loss(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Masked mean of the distillation losses, summed (gradients reach heads and torso): KL for
        the action task, 1 - cos (or MSE) for each text task."""
        mask, target, emb = _clean(batch)
        losses = {}
        if "action" in self.tasks:
            kl = (torch.xlogy(target, target) - target * batch["action_logits"].log_softmax(-1)).sum(-1)
            losses["action"] = kl
        for task, (pred, goal) in self._text_blocks(batch["summary"], emb).items():
            if self.summary_loss == "cosine":
                losses[task] = 1.0 - cosine(pred, goal)
            else:
                losses[task] = (pred - goal).pow(2).mean(-1)
        means = {t: _masked_mean(torch.where(mask, x, 0.0), mask) for t, x in losses.items()}
        # the logs stay tensors (the trainer syncs once per update, not per minibatch)
        return sum(means.values()), {f"distill_{t}": v.detach() for t, v in means.items()}

    def state_dict(self) -> dict:
        return {f"norm_{_suffix(t)}": norm.state_dict() for t, norm in self.norms.items()}

    def load_state_dict(self, state: dict) -> None:
        for t, norm in self.norms.items():
            norm.load_state_dict(state[f"norm_{_suffix(t)}"])
