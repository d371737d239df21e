"""Random Network Distillation (Burda, Edwards, Storkey and Klimov, "Exploration by Random Network
Distillation", ICLR 2019): pay the error of a trained predictor against a frozen random network.

Method `rnd` (registry.py); settings `RNDConfig` (`illm train --method rnd --bonus-option KEY=VALUE`).
Reads `next_images` only (see base.py); needs no LLM targets and no iLLM heads.

Settings follow CleanRL's `cleanrl/ppo_rnd_envpool.py` (github.com/vwxyzjn/cleanrl; docs at
docs.cleanrl.dev/rl-algorithms/ppo-rnd), the reference most users know:
- a frozen, randomly initialised target network f and a predictor f^ trained to match it; the
  intrinsic reward of transition t is the predictor's error on the observation it leads to,
  r_t = mean_k (f^(o_{t+1}) - f(o_{t+1}))_k^2 (CleanRL: the sum / 2, a constant factor that the
  normalisation below cancels);
- observation normalisation: an element-wise running mean / std of the observations (one per
  cell and channel), inputs (o - mean) / std clipped to [-5, 5] (`obs_clip`), for both networks;
- the reward is divided by the running std of its discounted intrinsic return (int_gamma 0.99,
  per-env filter never reset, mean not subtracted), `normalize.DiscountedReturnNormalizer`, which
  iLLM uses too (it accumulates over time per env, as openai/random-network-distillation does;
  CleanRL's loop runs over the env axis, cleanrl issue #360);
- the predictor's loss is the same squared error on a random `update_proportion` = 0.25 of each
  minibatch's samples (RND slows the predictor so the bonus does not vanish at once), over
  `epochs` x `minibatches` = 4 x 4 shuffled minibatches of the rollout, Adam lr 1e-4 (eps 1e-5),
  gradient norm clipped to 0.5;
- the trainer's non-episodic intrinsic value head (int_episodic False) takes the reward, and the
  advantages are summed with RND's weights ext_coef 2, int_coef 1: `illm train --method rnd` uses
  `--bonus-preset rnd` unless told otherwise (library users: `illm_tools.rl.build.run_config(
  {"method": "rnd", ...})` expands the method's preset as the command line does). The extrinsic
  gamma stays the run's (0.99; RND's Atari runs: 0.999).

Where this differs from CleanRL, on purpose:
- the networks. CleanRL's are Atari convnets (8x8 stride-4 kernels on 84x84 frames) that a 7x7
  input cannot feed. MiniGrid's egocentric view is 7 x 7 x 3 = 147 small integer codes whose
  position matters (the cell in front of the agent is not the one beside it), so both networks are
  MLPs on the 147 normalised inputs: target Linear-LeakyReLU-Linear-LeakyReLU-Linear, predictor the
  same plus two more ReLU layers (as CleanRL's predictor adds two layers to the target's), hidden
  256, output 128, orthogonal init (gain sqrt 2). At this size the MLP is cheaper than a conv stack
  and sees every cell with its position (MiniHack's glyph array is read the same way). On pictures
  CleanRL's convnets are used (`rnd_conv_networks`): Atari's newest frame, as CleanRL, or Crafter's
  RGB picture, with output 128;
- the observation statistics start from the first rollout (its next observations update them
  before its rewards are computed); CleanRL first steps a random policy for 50 rollouts. Later
  rollouts are rewarded with the statistics as they were, then merged in, as in CleanRL;
- the predictor trains on the observations it is paid for (next observations; CleanRL's loss uses
  the current ones, one step apart), with its own optimiser and a constant learning rate (CleanRL's
  shares the policy's optimiser and its annealing); the mission is not an input.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from illm_tools.errors import UsageError
from illm_tools.intrinsic.base import BonusContext, BonusRewards, IntrinsicBonus
from illm_tools.intrinsic.normalize import DiscountedReturnNormalizer, RunningMeanStd


@dataclass
class RNDConfig:
    """RND's settings (defaults: CleanRL's ppo_rnd_envpool.py where it has one)."""

    update_proportion: float = 0.25
    """Share of each minibatch's samples the predictor's loss uses (CleanRL: 0.25)."""
    predictor_lr: float = 1e-4
    """Adam learning rate of the predictor (CleanRL: 1e-4, eps 1e-5)."""
    epochs: int = 4
    """Passes of the predictor over each rollout (CleanRL: update_epochs 4)."""
    minibatches: int = 4
    """Minibatches per pass (CleanRL: num_minibatches 4)."""
    max_grad_norm: float = 0.5
    """Gradient norm clip of the predictor (CleanRL: 0.5)."""
    obs_clip: float = 5.0
    """Normalised observations are clipped to [-obs_clip, obs_clip] (RND: 5)."""
    hidden: int = 256
    """Hidden units of the target and predictor MLPs (on pictures the predictor's layers have 512,
    as CleanRL's)."""
    output_dim: int = 512
    """Size of the random features the predictor regresses (RND's paper and CleanRL: 512)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.update_proportion <= 1.0:
            raise UsageError(f"update_proportion must lie in (0, 1], got {self.update_proportion}")
        for name in ("predictor_lr", "epochs", "minibatches", "max_grad_norm", "obs_clip", "hidden", "output_dim"):
            if getattr(self, name) <= 0:
                raise UsageError(f"RND's {name} must be positive, got {getattr(self, name)}")


def _linear(inp: int, out: int) -> nn.Linear:
    layer = nn.Linear(inp, out)
    nn.init.orthogonal_(layer.weight, math.sqrt(2))
    nn.init.zeros_(layer.bias)
    return layer


def rnd_networks(inp: int, hidden: int, out: int) -> tuple[nn.Sequential, nn.Sequential]:
    """(target, predictor) MLPs on `inp` normalised inputs (see the module docstring)."""
    torso = lambda: [_linear(inp, hidden), nn.LeakyReLU(), _linear(hidden, hidden), nn.LeakyReLU(),  # noqa: E731
                     _linear(hidden, out)]
    target = nn.Sequential(*torso())
    predictor = nn.Sequential(*torso(), nn.ReLU(), _linear(out, out), nn.ReLU(), _linear(out, out))
    return target, predictor


def _conv(inp: int, out: int, kernel: int, stride: int) -> nn.Conv2d:
    layer = nn.Conv2d(inp, out, kernel, stride)
    nn.init.orthogonal_(layer.weight, math.sqrt(2))
    nn.init.zeros_(layer.bias)
    return layer


def rnd_conv_networks(shape: tuple[int, int, int], hidden: int, out: int) -> tuple[nn.Sequential, nn.Sequential]:
    """(target, predictor) on pictures [B, C, H, W], CleanRL's Atari networks: three LeakyReLU
    convolutions (32 8x8/4, 64 4x4/2, 64 3x3/1), then a linear layer for the target; the predictor
    adds two ReLU layers of `hidden` units (CleanRL: 512)."""
    convs = lambda: [_conv(shape[0], 32, 8, 4), nn.LeakyReLU(), _conv(32, 64, 4, 2), nn.LeakyReLU(),  # noqa: E731
                     _conv(64, 64, 3, 1), nn.LeakyReLU(), nn.Flatten()]
    with torch.no_grad():
        flat = nn.Sequential(*convs())(torch.zeros(1, *shape)).shape[1]
    target = nn.Sequential(*convs(), _linear(flat, out))
    predictor = nn.Sequential(*convs(), _linear(flat, hidden), nn.ReLU(), _linear(hidden, hidden), nn.ReLU(),
                              _linear(hidden, out))
    return target, predictor


class RNDBonus(IntrinsicBonus):
    """RND on the observation image (see the module docstring). The networks' initial weights come
    from torch's global RNG (the trainer seeds it with `ctx.seed` under `fork_rng`); the predictor's
    minibatch order and sample mask from its own generator seeded with `ctx.seed`."""

    config_class = RNDConfig

    def __init__(self, config: RNDConfig, ctx: BonusContext):
        self.config = config
        self.image_shape = tuple(ctx.image_shape)
        self.observation = ctx.observation
        self.input_shape = self._pictures(torch.zeros(1, *self.image_shape, dtype=torch.uint8)).shape[1:]
        if self.observation.rnd_picture:
            self.target, self.predictor = rnd_conv_networks(tuple(self.input_shape), 512, config.output_dim)
        else:
            self.target, self.predictor = rnd_networks(int(np.prod(self.image_shape)), config.hidden,
                                                       config.output_dim)
        self.target.requires_grad_(False)  # frozen: never trained, never in an optimiser
        self.optimizer = torch.optim.Adam(self.predictor.parameters(), lr=config.predictor_lr, eps=1e-5)
        self.obs_rms = RunningMeanStd(shape=tuple(self.input_shape))
        self.reward_norm = DiscountedReturnNormalizer(ctx.num_envs, ctx.int_gamma)
        self.generator = torch.Generator().manual_seed(ctx.seed)

    # --- the model --------------------------------------------------------------------------
    def _pictures(self, images: torch.Tensor) -> torch.Tensor:
        """What the networks read of observations [..., *obs shape]: for stacked frames the newest
        one [B, 1, H, W] (as CleanRL), for an RGB picture [B, 3, H, W]; else the rows [B, *obs shape]."""
        return self.observation.rnd_input(images.reshape(-1, *self.image_shape))

    def normalise(self, images: torch.Tensor) -> torch.Tensor:
        """[..., *obs shape] -> float32, standardised and clipped: [B, C, H, W] for pictures,
        [B, prod(obs shape)] otherwise (MiniGrid: H * W * 3)."""
        x = self._pictures(images).double()
        mean = torch.as_tensor(self.obs_rms.mean, device=x.device)
        std = torch.as_tensor(self.obs_rms.var, device=x.device).sqrt()
        clip = self.config.obs_clip
        x = ((x - mean) / std).clamp(-clip, clip).float()
        return x if self.observation.rnd_picture else x.flatten(1)

    def prediction_error(self, x: torch.Tensor) -> torch.Tensor:
        """Per-row mean squared error of the predictor against the target on normalised rows."""
        with torch.no_grad():
            target = self.target(x)
        return (self.predictor(x) - target).pow(2).mean(-1)

    # --- hooks ------------------------------------------------------------------------------
    @torch.no_grad()
    def compute_rewards(self, batch: Mapping[str, torch.Tensor]) -> BonusRewards:
        images = batch["next_images"]
        t, n = images.shape[:2]
        first = self.obs_rms.count < 1  # statistics start from the first rollout
        if first:
            self.obs_rms.update(self._pictures(images))
        error = self.prediction_error(self.normalise(images)).view(t, n)
        if not first:  # rewarded with the statistics as they were, then merged in (CleanRL's order)
            self.obs_rms.update(self._pictures(images))
        logs = {"rnd_error": float(error.mean())}
        return self.normalised(error, self.reward_norm, logs)

    def update(self, batch: Mapping[str, torch.Tensor]) -> dict[str, float]:
        """Train the predictor on the rollout's next observations (see the module docstring)."""
        cfg = self.config
        x_all = self.normalise(batch["next_images"])
        size = x_all.shape[0]
        step = max(1, size // cfg.minibatches)
        losses = []
        for _epoch in range(cfg.epochs):
            order = torch.randperm(size, generator=self.generator).to(x_all.device)  # drawn on the CPU: seeded
            for start in range(0, size, step):
                error = self.prediction_error(x_all[order[start:start + step]])
                mask = (torch.rand(error.shape, generator=self.generator) < cfg.update_proportion).to(error)
                loss = (error * mask).sum() / mask.sum().clamp_min(1.0)
                self.optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(self.predictor.parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                losses.append(loss.detach())
        return {"rnd_predictor_loss": float(torch.stack(losses).mean())}  # one sync per update

    def state_dict(self) -> dict:
        return {"target": self.target.state_dict(), "predictor": self.predictor.state_dict(),
                "optimizer": self.optimizer.state_dict(), "obs_rms": self.obs_rms.state_dict(),
                "reward_norm": self.reward_norm.state_dict(), "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        self.target.load_state_dict(state["target"])
        self.predictor.load_state_dict(state["predictor"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.obs_rms.load_state_dict(state["obs_rms"])
        self.reward_norm.load_state_dict(state["reward_norm"])
        self.generator.set_state(state["generator"])
