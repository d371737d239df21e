"""Never Give Up (Badia, Sprechmann, Vitvitskyi, Guo, Piot, Kapturowski, Tieleman, Arjovsky, Pritzel,
Bolt and Blundell, "Never Give Up: Learning Directed Exploration Strategies", ICLR 2020): pay how
rarely this episode has seen what the agent reaches, in an embedding of what it controls, scaled up
where the state is new over the whole run.

Method `ngu` (registry.py); settings `NGUConfig` (`illm train --method ngu --bonus-option KEY=VALUE`).
Reads `images`, `next_images`, `actions` and `ends` (see base.py); needs no LLM targets and no iLLM
heads. Also owns `InverseDynamics` and `train_inverse_dynamics`, the learned embedding that APT
(apt.py) uses too.

The reward, r_t = r^episodic_t * min(max(alpha_t, 1), L), paper Section 2 and Algorithm 1
(Appendix A.1, the episodic reward step by step), with the paper's constants (Section 2 and the
appendix's hyper-parameters) as defaults:
- the embedding f is trained by inverse dynamics: h(f(x_t), f(x_{t+1})) predicts a_t, h one hidden
  layer and a softmax (paper Section 2, "siamese network"). Transitions that end an episode are
  left out: their next observation is the next episode's first (base.py);
- episodic memory: per env, the embeddings of the current episode's observations (the last
  `memory_capacity` = 30000 of them, the paper's capacity), emptied when the episode ends;
- for the k = 10 nearest neighbours of f(x) in the memory, the squared distances d_i^2 are divided
  by a running mean d_m^2 of such squared distances (updated with the rollout's before it is used,
  as Algorithm 1 updates it before normalising), clustered d = max(d - xi, 0) with cluster distance
  xi = 8e-3, turned into kernel values K = eps / (d + eps) with kernel epsilon eps = 1e-3 (Section
  2 writes 10^-3; rllte's default is 1e-4), and the similarity s = sqrt(sum K) + c
  with pseudo-count constant c = 1e-3 gives r^episodic = 1 / s, or 0 when s > s_m = 8 (maximum
  similarity). With fewer than k observations in the memory the sum runs over those there are;
- the life-long factor alpha = 1 + (err - mu_e) / sigma_e, err the RND error (rnd.py's networks,
  observation normalisation and predictor training, reused through an `RNDBonus`), mu_e / sigma_e
  a running mean / std of it, clipped to [1, L] with L = 5 (the paper's "RND clipping L").

The reference implementation learnt from is rllte's (github.com/RLE-Foundation/rllte,
`rllte/xplore/reward/ngu.py` and `pseudo_counts.py`, MIT licence; nothing copied): it also keeps a
running mean of the kNN squared distances for d_m^2 and trains the embedding by inverse dynamics.

Choices (documented here once):
- reward t is paid with transition t for the observation it reaches, x_{t+1} = `next_images`, as
  rnd.py pays, against a memory holding the episode's observations up to and including x_t (so
  standing still, x_{t+1} = x_t, is not novel). A transition that ends its episode pays 0: its next
  observation belongs to the next episode, whose memory is still empty, and the ended episode's
  last observation is not in the contract (rllte likewise pays 0 where the memory is empty);
- the memory is built from the rollout's tensors in `compute_rewards` (one batched embedding of
  the rollout, then per env one `torch.cdist` and `topk` of its T queries against its episode so
  far, episodes told apart by `ends`), not step by step in `observe`: the embedding only changes in
  `update`, so the rewards are the ones a per-step memory would give. The embeddings of an
  episode's earlier rollouts stay as they were computed (NGU's memory keeps what it stored);
- the embedding reads the grid as the policy's torso does (one-hot of object, colour and state of
  each cell); f is an MLP (hidden 128, output 32: rllte's latent_dim) in place of NGU's Atari
  convnet, trained with Adam (lr 1e-3, rllte's) on the rollout, `epochs` x `minibatches` = 1 x 8
  minibatches (rllte: one pass in batches of 256, what 8 minibatches of the default 2048-transition
  rollout are). The RND part keeps RND's own settings (`RNDConfig` defaults);
- the reward is divided by the running std of its discounted return (normalize.py), as every
  bonus here; NGU's own mixture of policies (beta, gamma per policy) is not reproduced: the
  trainer's intrinsic value stream and weights stand for it;
- the memory is not checkpointed: a resumed run's environments restart their episodes
  (`Trainer._restore`), so its episodic memories start empty. Everything else is (embedding,
  optimisers, RND, running statistics, random stream).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from illm_tools.errors import UsageError
from illm_tools.intrinsic.base import BonusContext, BonusRewards, IntrinsicBonus
from illm_tools.intrinsic.normalize import DiscountedReturnNormalizer, RunningMeanStd
from illm_tools.intrinsic.rnd import RNDBonus, RNDConfig
from illm_tools.envs.observations import Observation

EXACT = "donot_use_mm_for_euclid_dist"
"""`torch.cdist` mode that gives exactly 0 between equal rows (the matmul form leaves ~1e-3), so a
repeated observation is a repeated observation; the cost is a few tens of ms per 2048 x 2048."""


# --- the inverse-dynamics embedding (NGU's f, APT's representation) ------------------------------
class InverseDynamics(nn.Module):
    """Embedding f (observation -> `embedding_dim`) and inverse model h (one hidden layer on
    [f(x_t), f(x_{t+1})] -> logits over the actions), trained so that h predicts a_t. f is the
    observation adapter's learned encoder (`illm_tools.envs.observations`: MiniGrid's grid one-hot
    encoded into an MLP; pictures through the Nature CNN, as NGU's Atari embedding is a convnet;
    MiniHack's glyphs through a learned embedding per position into an MLP)."""

    def __init__(self, observation: Observation, num_actions: int, hidden: int, embedding_dim: int):
        super().__init__()
        self.image_shape = tuple(observation.shape)
        self.embed = observation.encoder(hidden, embedding_dim)
        self.inverse = nn.Sequential(nn.Linear(2 * embedding_dim, hidden), nn.ReLU(), nn.Linear(hidden, num_actions))

    def load_state_dict(self, state: Mapping[str, torch.Tensor], strict: bool = True, assign: bool = False):
        """Also the names a checkpoint from before the observation adapters used (the encoder's
        input step was not a module then: `embed.i` is now `embed.i+1`, `glyphs` is `embed.0.glyphs`),
        so those NGU and APT runs still resume."""
        if set(state) != set(self.state_dict()):  # an older checkpoint's names
            renamed = {}
            for key, value in state.items():
                if key == "glyphs.weight":
                    key = "embed.0.glyphs.weight"
                elif key.startswith("embed."):
                    index, rest = key[len("embed."):].split(".", 1)
                    key = f"embed.{int(index) + 1}.{rest}"
                renamed[key] = value
            state = renamed
        return super().load_state_dict(state, strict=strict, assign=assign)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """f: [..., *obs shape] -> float32 [..., embedding_dim]."""
        lead = images.shape[:images.dim() - len(self.image_shape)]
        return self.embed(images.reshape(-1, *self.image_shape)).view(*lead, -1)

    def action_logits(self, images: torch.Tensor, next_images: torch.Tensor) -> torch.Tensor:
        """h(f(x_t), f(x_{t+1})): [B, A] logits of the action taken between the two."""
        return self.inverse(torch.cat([self(images), self(next_images)], -1))


def train_inverse_dynamics(model: InverseDynamics, optimizer: torch.optim.Optimizer, batch: Mapping[str, torch.Tensor],
                           *, epochs: int, minibatches: int, max_grad_norm: float,
                           generator: torch.Generator) -> dict[str, float]:
    """`epochs` passes of `minibatches` shuffled minibatches of the rollout's transitions, cross-entropy
    of h's logits against the action taken; transitions that end an episode are left out (their
    next observation is the next episode's first). Returns the mean loss and accuracy."""
    keep = batch["ends"].reshape(-1) == 0
    images = batch["images"].reshape(-1, *model.image_shape)[keep]
    next_images = batch["next_images"].reshape(-1, *model.image_shape)[keep]
    actions = batch["actions"].reshape(-1)[keep].long()
    size = actions.shape[0]
    if size == 0:
        return {}
    step = max(1, size // minibatches)
    losses, hits = [], []
    for _epoch in range(epochs):
        order = torch.randperm(size, generator=generator).to(actions.device)  # drawn on the CPU: seeded
        for start in range(0, size, step):
            rows = order[start:start + step]
            logits = model.action_logits(images[rows], next_images[rows])
            loss = F.cross_entropy(logits, actions[rows])
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), max_grad_norm)
            optimizer.step()
            losses.append(loss.detach())
            hits.append((logits.argmax(-1) == actions[rows]).float().mean())
    return {"loss": float(torch.stack(losses).mean()), "accuracy": float(torch.stack(hits).mean())}


@dataclass
class EmbeddingSettings:
    """Settings of the inverse-dynamics embedding, shared by NGU and APT."""

    embedding_dim: int = 32
    """Size of the embedding f (rllte's latent_dim: 32)."""
    hidden: int = 128
    """Hidden units of f and of the inverse model h."""
    embedding_lr: float = 1e-3
    """Adam learning rate of f and h (rllte: 1e-3)."""
    epochs: int = 1
    """Passes of the embedding's training over each rollout (rllte: one)."""
    minibatches: int = 8
    """Minibatches per pass (8 of the default 2048-transition rollout: rllte's batches of 256)."""
    max_grad_norm: float = 0.5
    """Gradient norm clip of the embedding's training."""

    def _check_embedding(self, who: str) -> None:
        for name in ("embedding_dim", "hidden", "embedding_lr", "epochs", "minibatches", "max_grad_norm"):
            if getattr(self, name) <= 0:
                raise UsageError(f"{who}'s {name} must be positive, got {getattr(self, name)}")


class EmbeddingBonus:
    """Mixin of the bonuses that learn an inverse-dynamics embedding (NGU, APT): the model
    `embedding`, its Adam optimiser and the generator of its minibatch order, trained on each
    rollout, saved in the bonus's state under "embedding", "optimizer" and "generator"."""

    def build_embedding(self, settings: EmbeddingSettings, ctx: BonusContext) -> None:
        self.embedding = InverseDynamics(ctx.observation, ctx.num_actions, settings.hidden, settings.embedding_dim)
        self.optimizer = torch.optim.Adam(self.embedding.parameters(), lr=settings.embedding_lr)
        self.generator = torch.Generator().manual_seed(ctx.seed + 1)
        self._embedding_settings = settings

    def fit_embedding(self, batch: Mapping[str, torch.Tensor], prefix: str) -> dict[str, float]:
        """Train the embedding by inverse dynamics on the rollout; its losses, named `prefix`_..."""
        cfg = self._embedding_settings
        fit = train_inverse_dynamics(self.embedding, self.optimizer, batch, epochs=cfg.epochs,
                                     minibatches=cfg.minibatches, max_grad_norm=cfg.max_grad_norm,
                                     generator=self.generator)
        return {f"{prefix}_embedding_{k}": v for k, v in fit.items()}

    def embedding_state(self) -> dict:
        return {"embedding": self.embedding.state_dict(), "optimizer": self.optimizer.state_dict(),
                "generator": self.generator.get_state()}

    def load_embedding_state(self, state: dict) -> None:
        self.embedding.load_state_dict(state["embedding"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])


def check_k(who: str, k: int, available: int, what: str) -> None:
    """One line refusing k nearest neighbours out of fewer than k candidates (`what` names them,
    with a {} for their number)."""
    if k <= 0:
        raise UsageError(f"{who}'s k must be positive, got {k}")
    if k > available:
        raise UsageError(f"{who}'s k = {k} is larger than {what.format(available)}: lower k")


# --- NGU -----------------------------------------------------------------------------------------
@dataclass
class NGUConfig(EmbeddingSettings):
    """NGU's settings (defaults: the paper's constants, Section 2 and Algorithm 1, where it has one)."""

    k: int = 10
    """Nearest neighbours in the episodic memory (paper: 10)."""
    kernel_epsilon: float = 1e-3
    """Kernel constant eps of K = eps / (d + eps) (paper: 10^-3)."""
    cluster_distance: float = 8e-3
    """Cluster distance xi: normalised squared distances below it count as 0 (paper: 8e-3)."""
    pseudo_count: float = 1e-3
    """Pseudo-count constant c of s = sqrt(sum K) + c (paper: 1e-3)."""
    max_similarity: float = 8.0
    """Maximum similarity s_m: above it the episodic reward is 0 (paper: 8)."""
    max_modulation: float = 5.0
    """L: the life-long factor alpha is clipped to [1, L] (paper: 5)."""
    memory_capacity: int = 30_000
    """Embeddings an env's episodic memory holds, the episode's latest (paper: 30000)."""
    lifelong: bool = True
    """Scale by RND's life-long factor; False: the episodic reward alone (alpha = 1)."""

    def __post_init__(self) -> None:
        self._check_embedding("NGU")
        for name in ("kernel_epsilon", "pseudo_count", "max_similarity", "memory_capacity"):
            if getattr(self, name) <= 0:
                raise UsageError(f"NGU's {name} must be positive, got {getattr(self, name)}")
        if self.cluster_distance < 0:
            raise UsageError(f"NGU's cluster_distance must be >= 0, got {self.cluster_distance}")
        if self.max_modulation < 1:
            raise UsageError(f"NGU's max_modulation L must be >= 1, got {self.max_modulation}")
        check_k("NGU", self.k, self.memory_capacity, "the {} embeddings an episodic memory holds (memory_capacity)")


class NGUBonus(EmbeddingBonus, IntrinsicBonus):
    """NGU's episodic novelty times RND's life-long factor (see the module docstring). Initial
    weights come from torch's global RNG (the trainer seeds it with `ctx.seed`); minibatch order
    from the bonus's own generator."""

    config_class = NGUConfig

    def __init__(self, config: NGUConfig, ctx: BonusContext):
        self.config = config
        self.num_envs = ctx.num_envs
        self.build_embedding(config, ctx)
        self.rnd = RNDBonus(RNDConfig(), ctx) if config.lifelong else None
        self.dist_rms = RunningMeanStd()   # d_m^2: the kNN squared distances
        self.error_rms = RunningMeanStd()  # mu_e, sigma_e: RND's error
        self.reward_norm = DiscountedReturnNormalizer(ctx.num_envs, ctx.int_gamma)
        self.memory = [torch.zeros(0, config.embedding_dim) for _ in range(ctx.num_envs)]
        """Per env, the embeddings of its current episode's observations so far (before this rollout)."""

    # --- episodic novelty -------------------------------------------------------------------
    @torch.no_grad()
    def episodic_rewards(self, embedded: torch.Tensor, reached: torch.Tensor, ends: torch.Tensor) -> torch.Tensor:
        """r^episodic [T, N] of reaching `reached` ([T, N, p] = f(x_{t+1})) given `embedded`
        ([T, N, p] = f(x_t)) and `ends` [T, N]; advances the memories past the rollout."""
        cfg = self.config
        t, n, _ = embedded.shape
        device = embedded.device
        steps = torch.arange(t, device=device)
        knn = torch.full((n, t, cfg.k), float("inf"), device=device)  # squared distances to each query's k nearest
        for i in range(n):  # one env at a time: a [T, memory + T] distance matrix, however long its episode
            carried = len(self.memory[i])
            cand = torch.cat([self.memory[i].to(device), embedded[:, i]])  # its episode so far, then x_0 .. x_{T-1}
            position = torch.arange(-carried, t, device=device)
            end = ends[:, i].long()
            episode = torch.cumsum(end, 0) - end  # episodes ended before step j: x_j's (the carried ones: 0)
            cand_episode = torch.cat([torch.zeros(carried, dtype=torch.long, device=device), episode])
            query_episode = episode + end  # an ending step reaches the next episode's first observation
            lag = steps[:, None] - position[None, :]  # t - j: the memory of query t holds x_j, j <= t
            usable = (cand_episode[None, :] == query_episode[:, None]) & (lag >= 0) & (lag < cfg.memory_capacity)
            d2 = torch.cdist(reached[:, i], cand, compute_mode=EXACT).pow(2).masked_fill(~usable, float("inf"))
            k = min(cfg.k, len(cand))
            knn[i, :, :k] = d2.topk(k, dim=-1, largest=False).values
            ended = torch.nonzero(end).flatten()  # the memory after the rollout: the ongoing episode's
            kept = cand[carried + int(ended[-1]) + 1:] if ended.numel() else cand
            self.memory[i] = kept[-cfg.memory_capacity:].clone()
        found = torch.isfinite(knn)
        if found.any():  # Algorithm 1: the moving average is updated, then used
            self.dist_rms.update(knn[found])
        d = (knn / (float(self.dist_rms.mean) + 1e-8) - cfg.cluster_distance).clamp_min(0.0)
        kernel = torch.where(found, cfg.kernel_epsilon / (d + cfg.kernel_epsilon), torch.zeros_like(d))
        s = kernel.sum(-1).sqrt() + cfg.pseudo_count
        reward = torch.where((s > cfg.max_similarity) | ~found.any(-1), torch.zeros_like(s), 1.0 / s)
        return reward.T

    @torch.no_grad()
    def lifelong_factor(self, reached_images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(min(max(alpha, 1), L), RND's error) [T, N] for the observations reached (uint8 [T, N, H, W, 3])."""
        rnd, t, n = self.rnd, *reached_images.shape[:2]
        first = rnd.obs_rms.count < 1  # as rnd.py: statistics start from the first rollout, later merged after
        if first:
            rnd.obs_rms.update(reached_images)
        error = rnd.prediction_error(rnd.normalise(reached_images)).view(t, n)
        if not first:
            rnd.obs_rms.update(reached_images)
        self.error_rms.update(error)
        alpha = 1.0 + (error - float(self.error_rms.mean)) / (self.error_rms.std + 1e-8)
        return alpha.clamp(1.0, self.config.max_modulation), error

    # --- hooks ------------------------------------------------------------------------------
    @torch.no_grad()
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        images, reached, ends = batch["images"], batch["next_images"], batch["ends"]
        episodic = self.episodic_rewards(self.embedding(images), self.embedding(reached), ends)
        logs = {"ngu_episodic": float(episodic.mean()), "ngu_dist_mean": float(self.dist_rms.mean)}
        raw = episodic
        if self.rnd is not None:
            factor, error = self.lifelong_factor(reached)
            raw = episodic * factor
            logs.update(ngu_lifelong=float(factor.mean()), rnd_error=float(error.mean()))
        return self.normalised(raw, self.reward_norm, logs)

    def update(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        """Train the embedding by inverse dynamics, and RND's predictor (rnd.py), on the rollout."""
        logs = self.fit_embedding(batch, "ngu")
        if self.rnd is not None:
            logs.update(self.rnd.update(batch))
        return logs

    def state_dict(self) -> dict:
        state = {**self.embedding_state(), "dist_rms": self.dist_rms.state_dict(),
                 "error_rms": self.error_rms.state_dict(), "reward_norm": self.reward_norm.state_dict()}
        if self.rnd is not None:
            state["rnd"] = self.rnd.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.load_embedding_state(state)
        self.dist_rms.load_state_dict(state["dist_rms"])
        self.error_rms.load_state_dict(state["error_rms"])
        self.reward_norm.load_state_dict(state["reward_norm"])
        if self.rnd is not None:
            self.rnd.load_state_dict(state["rnd"])
        # the episodic memories stay empty: a resumed run's environments restart their episodes
