"""Rollout storage and advantage estimation for PPO.

Owns `Rollout` (preallocated [T, N, ...] tensors of one rollout: what the loss reads and what
every intrinsic bonus may read, `illm_tools.intrinsic.base`; LLM targets included),
`gae` (generalised advantage estimation) and `two_stream_advantages` (RND-style extrinsic +
intrinsic streams, each with its own value head and GAE, summed with coefficients).

Convention: `ends[t]` is True when the transition taken at step t ended its episode
(terminated or truncated; truncation is treated like termination, as in CleanRL, because the
pool autoresets in the same step and does not return the final observation). For the same
reason `next_images[t]` / `next_missions[t]`, the observation after step t, is the first
observation of the next episode where `ends[t]` is set (as CleanRL's next_obs is); for the last
step it is the observation the next rollout starts from.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

BONUS_FIELDS = ("images", "missions", "actions", "ends", "next_images", "next_missions", "features")
"""The rollout fields every intrinsic bonus may read (illm_tools.intrinsic.base documents them)."""
TARGET_FIELDS = ("target_probs", "target_emb", "target_mask")
"""The LLM targets, added for bonuses that declare `needs_targets`."""


@dataclass
class Rollout:
    """One rollout of T steps from N envs. Targets are filled after the rollout."""

    images: torch.Tensor       # [T, N, *obs shape] the observation acted from (the suite's dtype)
    missions: torch.Tensor     # int64 [T, N, L]
    next_images: torch.Tensor  # [T, N, *obs shape] the observation after the step (see module doc)
    next_missions: torch.Tensor  # int64 [T, N, L]
    actions: torch.Tensor      # int64 [T, N]
    logprobs: torch.Tensor     # float [T, N]
    rewards: torch.Tensor      # float [T, N] extrinsic
    ends: torch.Tensor         # float [T, N] 1.0 where the episode ended at this step
    values_ext: torch.Tensor   # float [T, N]
    values_int: torch.Tensor   # float [T, N]
    target_probs: torch.Tensor  # float [T, N, A] LLM distribution over valid actions
    target_emb: torch.Tensor    # float [T, N, D] LLM summary embedding
    target_mask: torch.Tensor   # bool [T, N]
    features: torch.Tensor      # float [T, N, F] policy features at acting time
    contexts: torch.Tensor      # float [T, N, C] what the network read beside the observation (hop: Z_h; C = 0 else)

    @classmethod
    def empty(cls, num_steps: int, num_envs: int, image_shape: tuple[int, ...], mission_len: int,
              num_actions: int, embedding_dim: int, feature_dim: int = 0,
              image_dtype: torch.dtype = torch.uint8, context_dim: int = 0,
              device: torch.device | str = "cpu") -> "Rollout":
        t, n = num_steps, num_envs
        z = lambda *shape, dtype=torch.float32: torch.zeros((t, n, *shape), dtype=dtype, device=device)  # noqa: E731
        return cls(
            images=z(*image_shape, dtype=image_dtype), missions=z(mission_len, dtype=torch.int64),
            next_images=z(*image_shape, dtype=image_dtype), next_missions=z(mission_len, dtype=torch.int64),
            actions=z(dtype=torch.int64), logprobs=z(), rewards=z(), ends=z(),
            values_ext=z(), values_int=z(), target_probs=z(num_actions),
            target_emb=z(embedding_dim), target_mask=z(dtype=torch.bool), features=z(feature_dim),
            contexts=z(context_dim),
        )

    @property
    def num_steps(self) -> int:
        return self.actions.shape[0]

    def flat(self, name: str) -> torch.Tensor:
        """Field `name` with the T and N axes merged: [T * N, ...]."""
        x = getattr(self, name)
        return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])  # explicit: a field may be empty ([T, N, 0])

    def bonus_batch(self, targets: bool, rows: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """What a bonus reads: `BONUS_FIELDS` (+ `TARGET_FIELDS` when `targets`), [T, N, ...]
        views, or the flat rows `rows` ([B, ...]) when given."""
        names = BONUS_FIELDS + (TARGET_FIELDS if targets else ())
        if rows is None:
            return {name: getattr(self, name) for name in names}
        return {name: self.flat(name)[rows] for name in names}


def gae(rewards: torch.Tensor, values: torch.Tensor, next_value: torch.Tensor, ends: torch.Tensor,
        gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE(gamma, lambda) over [T, N] tensors; returns (advantages, returns = advantages + values).

    `next_value` [N] is the value of the observation after the last step; `ends` cuts the
    bootstrap (pass zeros for a non-episodic stream).
    """
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(next_value)
    for t in reversed(range(rewards.shape[0])):
        nonterminal = 1.0 - ends[t]
        following = next_value if t == rewards.shape[0] - 1 else values[t + 1]
        delta = rewards[t] + gamma * following * nonterminal - values[t]
        last = delta + gamma * lam * nonterminal * last
        advantages[t] = last
    return advantages, advantages + values


@dataclass
class Advantages:
    """What the PPO loss consumes: the summed advantage and a return target per value head; and
    the two weighted parts of the sum, to watch the bonus's scale."""

    advantages: torch.Tensor   # [T, N] ext_part + int_part
    returns_ext: torch.Tensor  # [T, N]
    returns_int: torch.Tensor  # [T, N] (zeros without a bonus)
    ext_part: torch.Tensor     # [T, N] ext_coef * A_ext
    int_part: torch.Tensor     # [T, N] int_coef * A_int (zeros without a bonus)

    def scale_logs(self) -> dict[str, float]:
        """How big the bonus is next to the task reward, per update: mean |ext_coef A_ext| and
        mean |int_coef A_int| (`adv_ext_abs`, `adv_int_abs`), their ratio `adv_int_ext_ratio`
        (int / max(ext, 1e-8); above 1 the bonus steers the normalised advantage more than the
        task does, and it is the bonus alone while no episode has paid a reward), and the mean GAE
        return of each stream (`return_ext`, `return_int`, the latter in normalised-bonus units)."""
        ext, intr = float(self.ext_part.abs().mean()), float(self.int_part.abs().mean())
        return {"adv_ext_abs": ext, "adv_int_abs": intr, "adv_int_ext_ratio": intr / max(ext, 1e-8),
                "return_ext": float(self.returns_ext.mean()), "return_int": float(self.returns_int.mean())}


def two_stream_advantages(ro: Rollout, int_rewards: torch.Tensor | None, next_value_ext: torch.Tensor,
                          next_value_int: torch.Tensor, *, gamma: float, int_gamma: float, lam: float,
                          ext_coef: float, int_coef: float, int_episodic: bool) -> Advantages:
    """Extrinsic GAE on the env reward plus, when `int_rewards` is given, intrinsic GAE on it.

    The bonus enters here, after it is computed and before the loss reads the advantages
    (the order rllte got wrong). Without a bonus the intrinsic stream is absent (zeros).
    """
    adv_ext, ret_ext = gae(ro.rewards, ro.values_ext, next_value_ext, ro.ends, gamma, lam)
    if int_rewards is None:
        zeros = torch.zeros_like(ret_ext)
        return Advantages(ext_coef * adv_ext, ret_ext, zeros, ext_coef * adv_ext, zeros)
    int_ends = ro.ends if int_episodic else torch.zeros_like(ro.ends)
    adv_int, ret_int = gae(int_rewards, ro.values_int, next_value_int, int_ends, int_gamma, lam)
    ext_part, int_part = ext_coef * adv_ext, int_coef * adv_int
    return Advantages(ext_part + int_part, ret_ext, ret_int, ext_part, int_part)
