"""The noisy TV (paper Table 4): with probability rho per step, a 32x32 patch of independent uniform
noise in [0, 255] covers the lower-right corner of the observation; otherwise it is untouched.

Curiosity bonuses that pay for unpredictable observations are drawn to such a patch; a bonus that
asks whether the LLM would agree with the agent should not be. `NoisyTV` wraps an env whose
observation is a grey frame (H, W) or an RGB picture (H, W, 3) (all channels noised); the suites
take it as `--env-option noisy_tv=<rho>` (Atari: each 84x84 frame before stacking, so the stack
holds the noised frames of their own steps; Crafter: the 64x64 picture). Its generator is seeded
from each episode's seed (so a seed gives the same noise), and keeps going without one.
"""
from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from illm_tools.errors import UsageError

PATCH = 32
_SALT = 0x7E1E  # separates the noise's stream from the env's own use of the seed


class NoisyTV(gym.ObservationWrapper):
    def __init__(self, env: gym.Env, rho: float, patch: int = PATCH):
        rho = float(rho)
        if not 0.0 <= rho <= 1.0:
            raise UsageError(f"noisy_tv is the probability of noise per step, in [0, 1]; got {rho}")
        super().__init__(env)
        shape = env.observation_space.shape
        if len(shape) not in (2, 3) or shape[0] < patch or shape[1] < patch:
            raise UsageError(f"the noisy TV covers a {patch}x{patch} corner of a frame or picture; this env's "
                             f"observation has shape {shape}")
        self.rho, self.patch = rho, int(patch)
        self.rng = np.random.default_rng()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.rng = np.random.default_rng([int(seed), _SALT])
        return super().reset(seed=seed, options=options)

    def observation(self, observation: Any) -> np.ndarray:
        if self.rho == 0.0 or self.rng.random() >= self.rho:
            return observation
        noised = np.array(observation, copy=True)
        region = noised[-self.patch:, -self.patch:]
        region[...] = self.rng.integers(0, 256, size=region.shape, dtype=np.uint8)
        return noised
