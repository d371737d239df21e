"""Active Pre-Training (Liu and Abbeel, "Behavior From the Void: Unsupervised Active Pre-Training",
NeurIPS 2021): pay the particle-based entropy estimate of where the agent goes, the mean distance to
its k nearest neighbours among the states of the same batch, in a learned representation.

Method `apt` (registry.py); settings `APTConfig` (`illm train --method apt --bonus-option KEY=VALUE`).
Reads `images`, `next_images`, `actions` and `ends` (see base.py); needs no LLM targets and no iLLM
heads.

The reward of transition t, for the observation it reaches (z = f(x_{t+1})):
  r = log(1 + (1/k) sum_{j in kNN(z)} ||z - z_j|| / m),
the k nearest neighbours taken among the rollout's other T x N reached observations (`torch.cdist`,
`topk`), m a running mean of those kNN distances, each normalised distance less `knn_clip` and
floored at 0 before the mean. This is the paper's r = log(c + mean kNN distance), c = 1, with the
normalisation of the authors' code in URLB (github.com/rll-research/url_benchmark, `utils.PBE` and
`agent/icm_apt.yaml`: knn_k 12, knn_avg true, knn_rms true, knn_clip 1e-4; nothing copied), whose
values are the defaults here.

Choices (documented here once):
- the representation is NGU's inverse-dynamics embedding (ngu.py: `InverseDynamics`, trained in
  `update` on the rollout's transitions, those that end an episode left out), as URLB's icm_apt
  trains its representation with ICM's inverse model; the paper's own representation is
  contrastive (and it pre-trains without extrinsic reward, which the trainer here pays as well);
- a point is not its own neighbour (URLB's topk includes the point itself at distance 0); a state
  repeated in the batch has its copies at distance 0, so a batch of one state pays 0 everywhere;
- reward t is paid for x_{t+1}, as rnd.py and ngu.py pay (URLB's for the replayed x_t); the
  running mean m is updated with the batch's distances before it divides them (URLB's order);
- the reward is then divided by the running std of its discounted return (normalize.py), as every
  bonus here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch

from illm_tools.errors import UsageError
from illm_tools.intrinsic.base import BonusContext, BonusRewards, IntrinsicBonus
from illm_tools.intrinsic.ngu import EXACT, EmbeddingBonus, EmbeddingSettings, check_k
from illm_tools.intrinsic.normalize import DiscountedReturnNormalizer, RunningMeanStd


@dataclass
class APTConfig(EmbeddingSettings):
    """APT's settings (defaults: URLB's apt configuration where it has one)."""

    k: int = 12
    """Nearest neighbours among the rollout's states (URLB's knn_k: 12)."""
    knn_clip: float = 1e-4
    """Subtracted from each normalised distance, floored at 0 (URLB's knn_clip: 1e-4)."""
    knn_rms: bool = True
    """Divide the distances by their running mean (URLB's knn_rms: true)."""

    def __post_init__(self) -> None:
        self._check_embedding("APT")
        if self.knn_clip < 0:
            raise UsageError(f"APT's knn_clip must be >= 0, got {self.knn_clip}")
        if self.k <= 0:  # the rollout's size is checked when the bonus is built (it needs the run's sizes)
            raise UsageError(f"APT's k must be positive, got {self.k}")


class APTBonus(EmbeddingBonus, IntrinsicBonus):
    """APT's particle-based entropy reward (see the module docstring). Initial weights come from
    torch's global RNG (the trainer seeds it with `ctx.seed`); minibatch order from the bonus's own
    generator."""

    config_class = APTConfig

    def __init__(self, config: APTConfig, ctx: BonusContext):
        check_k("APT", config.k, ctx.num_envs * ctx.num_steps - 1,
                "the {} other states of a rollout (num_envs x num_steps - 1)")
        self.config = config
        self.build_embedding(config, ctx)
        self.dist_rms = RunningMeanStd()  # m: the kNN distances
        self.reward_norm = DiscountedReturnNormalizer(ctx.num_envs, ctx.int_gamma)

    @torch.no_grad()
    def entropy_rewards(self, reached: torch.Tensor) -> torch.Tensor:
        """log(1 + mean normalised kNN distance) [T, N] of the embeddings `reached` [T, N, p];
        updates the running mean of the distances."""
        cfg = self.config
        t, n, p = reached.shape
        z = reached.reshape(t * n, p)
        dist = torch.cdist(z, z, compute_mode=EXACT)
        dist.fill_diagonal_(float("inf"))  # a point is not its own neighbour
        knn = dist.topk(cfg.k, dim=-1, largest=False).values  # [B, k]
        if cfg.knn_rms:
            self.dist_rms.update(knn)
            knn = knn / (float(self.dist_rms.mean) + 1e-8)
        knn = (knn - cfg.knn_clip).clamp_min(0.0)
        return torch.log1p(knn.mean(-1)).view(t, n)

    # --- hooks ------------------------------------------------------------------------------
    @torch.no_grad()
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        raw = self.entropy_rewards(self.embedding(batch["next_images"]))
        logs = {"apt_entropy": float(raw.mean()), "apt_dist_mean": float(self.dist_rms.mean)}
        return self.normalised(raw, self.reward_norm, logs)

    def update(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        """Train the representation by inverse dynamics on the rollout (ngu.py)."""
        return self.fit_embedding(batch, "apt")

    def state_dict(self) -> dict:
        return {**self.embedding_state(), "dist_rms": self.dist_rms.state_dict(),
                "reward_norm": self.reward_norm.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.load_embedding_state(state)
        self.dist_rms.load_state_dict(state["dist_rms"])
        self.reward_norm.load_state_dict(state["reward_norm"])
