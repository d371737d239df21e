"""Rollout storage and advantage estimation for PPO.

Owns `Rollout` (preallocated [T, N, ...] tensors of one rollout: what the loss reads and what
every intrinsic bonus may read, `illm_tools.intrinsic.base`; LLM targets included),
`gae` (generalised advantage estimation) and `two_stream_advantages` (RND-style extrinsic +
intrinsic streams, each with its own value head and GAE, summed with coefficients; or the paper's
one stream of r* = r + b with one critic), with `capped` (the intrinsic part held to a multiple of
the extrinsic one where the task pays).

Convention: `ends[t]` is True when the transition taken at step t ended its episode
(terminated or truncated; truncation is treated like termination, as in CleanRL, because the
pool autoresets in the same step and does not return the final observation). For the same
reason `next_images[t]` / `next_missions[t]`, the observation after step t, is the first
observation of the next episode where `ends[t]` is set (as CleanRL's next_obs is); for the last
step it is the observation the next rollout starts from. So `next_images[t]` is `images[t + 1]`
for every t < T - 1, and the rollout stores the T + 1 observations once (half the memory of two
copies).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch

BONUS_FIELDS = ("images", "missions", "actions", "ends", "next_images", "next_missions", "features")
"""The rollout fields every intrinsic bonus may read (illm_tools.intrinsic.base documents them); a
bonus also reads the rollout's named extras (the LLM targets, where the run has them)."""
TARGET_FIELDS = ("target_probs", "target_emb", "target_mask")
"""The LLM targets' extras, filled after the rollout for bonuses that declare `needs_targets`."""


def target_extras(num_actions: int, embedding_dim: int) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """The extras holding a run's LLM targets: the distribution over the valid actions [A], the text
    tasks' embeddings side by side [D], and whether the step has a target."""
    return {"target_probs": ((num_actions,), torch.float32), "target_emb": ((embedding_dim,), torch.float32),
            "target_mask": ((), torch.bool)}


@dataclass
class Rollout:
    """One rollout of T steps from N envs.

    The observations are stored once, T + 1 of them: step t acts from `observations[t]` and reaches
    `observations[t + 1]` (`images` and `next_images` are views of the two ranges, see the module
    docstring); the missions likewise. What a method or the run's state source adds per step lives
    in `extras` under its name ([T, N, ...] each, read as attributes: `ro.contexts`, `ro.target_probs`).
    """

    observations: torch.Tensor  # [T + 1, N, *obs shape] (the suite's dtype)
    mission_ids: torch.Tensor   # int64 [T + 1, N, L]
    actions: torch.Tensor       # int64 [T, N]
    logprobs: torch.Tensor      # float [T, N]
    rewards: torch.Tensor       # float [T, N] extrinsic
    ends: torch.Tensor          # float [T, N] 1.0 where the episode ended at this step
    values_ext: torch.Tensor    # float [T, N]
    values_int: torch.Tensor    # float [T, N]
    features: torch.Tensor      # float [T, N, F] policy features at acting time
    extras: dict[str, torch.Tensor] = field(default_factory=dict)
    """Named [T, N, ...] tensors: "contexts" (what the network read beside the observation: hop's
    Z_h), the LLM targets (`TARGET_FIELDS`)."""

    @classmethod
    def empty(cls, num_steps: int, num_envs: int, image_shape: tuple[int, ...], mission_len: int, *,
              feature_dim: int = 0, image_dtype: torch.dtype = torch.uint8,
              extras: Mapping[str, tuple[tuple[int, ...], torch.dtype]] | None = None,
              device: torch.device | str = "cpu") -> "Rollout":
        """Zeros; `extras`: name -> (per-step shape, dtype)."""
        t, n = num_steps, num_envs
        z = lambda *shape, dtype=torch.float32, steps=t: torch.zeros((steps, n, *shape), dtype=dtype,  # noqa: E731
                                                                     device=device)
        return cls(
            observations=z(*image_shape, dtype=image_dtype, steps=t + 1),
            mission_ids=z(mission_len, dtype=torch.int64, steps=t + 1),
            actions=z(dtype=torch.int64), logprobs=z(), rewards=z(), ends=z(), values_ext=z(), values_int=z(),
            features=z(feature_dim),
            extras={name: z(*shape, dtype=dtype) for name, (shape, dtype) in (extras or {}).items()},
        )

    images = property(lambda self: self.observations[:-1], doc="[T, N, *obs shape] the observation acted from")
    next_images = property(lambda self: self.observations[1:], doc="[T, N, *obs shape] the observation reached")
    missions = property(lambda self: self.mission_ids[:-1], doc="int64 [T, N, L] its mission's word ids")
    next_missions = property(lambda self: self.mission_ids[1:], doc="int64 [T, N, L] the next one's")

    def __getattr__(self, name: str) -> torch.Tensor:  # the extras, by name
        extras = self.__dict__.get("extras", {})
        if name in extras:
            return extras[name]
        raise AttributeError(f"the rollout has no field or extra {name!r}")

    @property
    def num_steps(self) -> int:
        return self.actions.shape[0]

    def flat(self, name: str) -> torch.Tensor:
        """Field `name` with the T and N axes merged: [T * N, ...]."""
        x = getattr(self, name)
        return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])  # explicit: a field may be empty ([T, N, 0])

    def bonus_batch(self, rows: torch.Tensor | None = None, names: Sequence[str] | None = None) -> dict[str, torch.Tensor]:
        """What a bonus reads: `names` (None: `BONUS_FIELDS` and the extras), [T, N, ...] views, or
        the flat rows `rows` ([B, ...]) when given."""
        names = BONUS_FIELDS + tuple(self.extras) if names is None else names
        if rows is None:
            return {name: getattr(self, name) for name in names}
        return {name: self.flat(name)[rows] for name in names}


def gae(rewards: torch.Tensor, values: torch.Tensor, next_value: torch.Tensor, ends: torch.Tensor,
        gamma: float | Sequence[float], lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE(gamma, lambda) over [T, N] tensors; returns (advantages, returns = advantages + values).

    `next_value` [N] is the value of the observation after the last step; `ends` cuts the
    bootstrap (pass zeros for a non-episodic stream). Several streams at once: [T, N, S] tensors
    (and [N, S] next values) with one `gamma` per stream, each stream's result the same, bit for
    bit, as its own call's (the discounts are the float32 numbers a lone call multiplies by), in
    one pass of the loop: 128 steps of a dozen small ops is 2.3 ms a stream on a CPU.
    """
    discount = torch.tensor(gamma if isinstance(gamma, (int, float)) else list(gamma), dtype=torch.float64)
    discount, trace = (f.to(rewards.device, rewards.dtype) for f in (discount, discount * lam))
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(next_value)
    for t in reversed(range(rewards.shape[0])):
        nonterminal = 1.0 - ends[t]
        following = next_value if t == rewards.shape[0] - 1 else values[t + 1]
        delta = rewards[t] + discount * following * nonterminal - values[t]
        last = delta + trace * nonterminal * last
        advantages[t] = last
    return advantages, advantages + values


def _gae_streams(streams: Sequence[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]],
                 gammas: Sequence[float], lam: float) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """`gae` of each (rewards, values, next value, ends) of `streams` with its gamma, in one loop."""
    stacked = [torch.stack(parts, -1) for parts in zip(*streams)]
    advantages, returns = gae(*stacked, gammas, lam)
    return list(zip(advantages.unbind(-1), returns.unbind(-1)))


@dataclass
class Advantages:
    """What the PPO loss consumes: the summed advantage and a return target per value head; and
    the two weighted parts of the sum, to watch the bonus's scale."""

    advantages: torch.Tensor   # [T, N] ext_part + int_part
    returns_ext: torch.Tensor  # [T, N] (one stream: the return of r* = ext_coef r + int_coef b)
    returns_int: torch.Tensor  # [T, N] (zeros without a bonus, and with one stream)
    ext_part: torch.Tensor     # [T, N] ext_coef * A_ext
    int_part: torch.Tensor     # [T, N] int_coef * A_int (zeros without a bonus)
    int_stream: bool = True
    """Whether the intrinsic value head has a return to learn (two streams and a bonus paid)."""
    int_scale: float = 1.0
    """The factor `int_ext_cap` put on the intrinsic part this rollout (1: not capped)."""

    def scale_logs(self) -> dict[str, float]:
        """How big the bonus is next to the task reward, per update: mean |ext_coef A_ext| and
        mean |int_coef A_int| (`adv_ext_abs`, `adv_int_abs`), their ratio `adv_int_ext_ratio`
        (int / max(ext, 1e-8); above 1 the bonus steers the normalised advantage more than the
        task does, and it is the bonus alone while no episode has paid a reward), the mean GAE
        return of each stream (`return_ext`, `return_int`, the latter in normalised-bonus units),
        and the cap's factor (`int_scale`)."""
        ext, intr = float(self.ext_part.abs().mean()), float(self.int_part.abs().mean())
        return {"adv_ext_abs": ext, "adv_int_abs": intr, "adv_int_ext_ratio": intr / max(ext, 1e-8),
                "return_ext": float(self.returns_ext.mean()), "return_int": float(self.returns_int.mean()),
                "int_scale": self.int_scale}


def capped(ext_part: torch.Tensor, int_part: torch.Tensor, cap: float) -> tuple[torch.Tensor, float]:
    """The intrinsic part scaled down so that its mean |.| is at most `cap` times the extrinsic
    part's, in a rollout where the task paid anything (mean |ext_part| > 0); else as it is. 0: no
    cap. The bonus steers alone while nothing is found, and gives way to the task's advantage,
    in proportion, where the task pays: a scale that follows the task's reward, with no per-level
    weight."""
    if cap <= 0:
        return int_part, 1.0
    ext, intr = float(ext_part.abs().mean()), float(int_part.abs().mean())
    if ext <= 0 or intr <= cap * ext:
        return int_part, 1.0
    scale = cap * ext / intr
    return int_part * scale, scale


def two_stream_advantages(ro: Rollout, int_rewards: torch.Tensor | None, next_value_ext: torch.Tensor,
                          next_value_int: torch.Tensor, *, gamma: float, int_gamma: float, lam: float,
                          ext_coef: float, int_coef: float, int_episodic: bool, streams: int = 2,
                          int_ext_cap: float = 0.0) -> Advantages:
    """Extrinsic GAE on the env reward plus, when `int_rewards` is given, the bonus's advantage.

    streams 2 (RND's): intrinsic GAE on the bonus with its own value head (`values_int`), its own
    discount and, unless `int_episodic`, no cut at episode ends; the two advantages summed with
    their coefficients. streams 1 (the paper's Algorithm 1, line 11): one reward r* = ext_coef r +
    int_coef b, one critic (`values_ext`), one episodic GAE at `gamma`; its intrinsic part is the
    (gamma lambda)-discounted sum of int_coef b within the episode (GAE is linear in the rewards,
    so ext_part = A(r*) - int_part exactly) and the intrinsic head learns nothing.
    `int_ext_cap` > 0 caps the intrinsic part at that multiple of the extrinsic one (`capped`).

    The bonus enters here, after it is computed and before the loss reads the advantages
    (the order rllte got wrong). Without a bonus the intrinsic stream is absent (zeros).
    """
    if streams not in (1, 2):
        raise ValueError(f"streams is 1 or 2, got {streams}")
    if int_rewards is None:
        adv_ext, ret_ext = gae(ro.rewards, ro.values_ext, next_value_ext, ro.ends, gamma, lam)
        zeros = torch.zeros_like(ret_ext)
        return Advantages(ext_coef * adv_ext, ret_ext, zeros, ext_coef * adv_ext, zeros, int_stream=False)
    if streams == 1:
        shaped = ext_coef * ro.rewards + int_coef * int_rewards
        zeros = torch.zeros_like(ro.values_ext)
        (adv, ret), (int_part, _) = _gae_streams([(shaped, ro.values_ext, next_value_ext, ro.ends),
                                                   (int_coef * int_rewards, zeros, zeros[0], ro.ends)], (gamma, gamma), lam)
        ext_part = adv - int_part
        int_part, scale = capped(ext_part, int_part, int_ext_cap)
        return Advantages(ext_part + int_part, ret, zeros, ext_part, int_part, int_stream=False, int_scale=scale)
    int_ends = ro.ends if int_episodic else torch.zeros_like(ro.ends)
    (adv_ext, ret_ext), (adv_int, ret_int) = _gae_streams([(ro.rewards, ro.values_ext, next_value_ext, ro.ends),
                                                           (int_rewards, ro.values_int, next_value_int, int_ends)],
                                                          (gamma, int_gamma), lam)
    ext_part = ext_coef * adv_ext
    int_part, scale = capped(ext_part, int_coef * adv_int, int_ext_cap)
    return Advantages(ext_part + int_part, ret_ext, ret_int, ext_part, int_part, int_scale=scale)
