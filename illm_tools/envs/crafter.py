"""Crafter (Hafner 2021): an open-ended 2-D survival world; the policy sees its 64x64 picture, the
LLM a text written by illm, and the score is Crafter's.

Env ids: `CrafterReward-v1` (the game's reward: +1 for each achievement unlocked for the first
time in an episode, +-0.1 per health point gained or lost) and `CrafterNoReward-v1` (reward 0,
for pure exploration), the ids crafter registers for the old gym API; here they are a gymnasium
env, `CrafterEnv`. `--env-option`s: area, view, size, length (crafter.Env's; length: steps before
an episode is cut, 10,000 by default), noisy_tv (paper Table 4's noise patch, `noisy_tv.py`). An episode ends when the player dies (terminated) or at
`length` (truncated). Each episode is generated from its own seed (the pool's episode seed).

The text (renderer "crafter-text@<version>", `crafter_text.render_text`): what the agent faces,
what is in view with direction and distance, the inventory, health/food/drink/energy. The score
(`crafter_text.crafter_score`): the geometric mean of the 22 achievements' success rates over the
episodes, exp(mean ln(1 + s_i)) - 1 with s_i in percent; each achievement's success rate is a
metric too (`achievement_<name>`). There is no success.

Stepping is slow (about 230 steps/s here, crafter does not use numba), so the pool runs Crafter
envs each in its own process (`vector = "async"`). crafter despawns creatures in set order, which
differs between processes; `CrafterEnv` orders them by position so that a seed gives one world.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from illm_tools.envs.suite import EpisodeStats, ObsSpec, Suite

ENV_IDS = {"CrafterReward-v1": True, "CrafterNoReward-v1": False}
"""Id -> whether the env pays the game's reward."""
OPTIONS = ("area", "view", "size", "length", "noisy_tv")


def _ordered_world(world: Any) -> None:
    """Make `world` list each chunk's objects sorted by position. crafter keeps them in a set, whose
    order differs between processes, and picks the creatures it despawns from it: without this the
    same seed and actions give other worlds in another process (seen in 2 of 6 runs of 25 steps)."""
    base = type(world)

    class OrderedWorld(base):
        @property
        def chunks(self):
            return {key: sorted(objs, key=lambda obj: tuple(obj.pos)) for key, objs in self._chunks.items()}

    world.__class__ = OrderedWorld


class CrafterEnv(gym.Env):
    """crafter.Env as a gymnasium env with illm's info keys (text, mission, valid_actions, and at an
    episode's end success None and the achievements)."""

    metadata: dict = {"render_modes": []}

    def __init__(self, reward: bool = True, render_text: bool = True, **options: Any):
        import crafter

        from illm_tools.envs import crafter_text

        self._env = crafter.Env(reward=reward, seed=0, **options)
        _ordered_world(self._env._world)
        self._text = crafter_text
        self.render_text = render_text
        self.action_names: tuple[str, ...] = crafter_text.ACTION_NAMES
        self.action_space = gym.spaces.Discrete(len(self.action_names))
        self.observation_space = gym.spaces.Box(0, 255, (*self._env._size, 3), np.uint8)

    def _info(self, info: dict) -> dict:
        info["text"] = self._text.render_text(self._env) if self.render_text else ""
        info["mission"] = self._text.MISSION
        info["valid_actions"] = list(self.action_names)
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:  # crafter seeds episode k of an env with hash((seed, k)); one episode per seed here
            self._env._seed, self._env._episode = int(seed), 0
        obs = self._env.reset()
        return obs, self._info({})

    def step(self, action: Any):
        obs, reward, done, info = self._env.step(int(action))
        terminated = bool(done and self._env._player.health <= 0)
        truncated = bool(done and not terminated)
        out = {}
        if done:
            out = {"success": None, "achievements": dict(info["achievements"])}
        return obs, float(reward), terminated, truncated, self._info(out)


def grey(rgb: np.ndarray) -> np.ndarray:
    """ITU-R 601 luma of an [H, W, 3] uint8 picture, rounded to uint8 [H, W]: the grey-scaling of
    OpenCV's COLOR_RGB2GRAY and ALE's grey screen, which Atari's frames go through (paper B.1:
    the Hopfield module reads grey-scaled observations)."""
    return np.rint(rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)).clip(0, 255).astype(np.uint8)


class CrafterSuite(Suite):
    name = "crafter"
    prefixes = ("Crafter",)
    score_name = "Crafter score"
    vector = "async"
    network = "frame"
    description = "Crafter (crafter), 64x64 RGB picture; text written by illm; Crafter score"

    def hop_frame(self, raw: np.ndarray) -> np.ndarray:
        return grey(raw)  # paper B.1: the Hopfield module reads grey-scaled observations, as Atari's frames

    @property
    def renderer(self) -> str:  # type: ignore[override]
        from illm_tools.envs.crafter_text import RENDERER_NAME, RENDERER_VERSION

        return f"{RENDERER_NAME}@{RENDERER_VERSION}"

    def env_ids(self) -> list[str]:
        return sorted(ENV_IDS)

    def options(self, env_id: str) -> tuple[str, ...]:
        return OPTIONS

    def make(self, env_id: str, *, action_space: str, render_text: bool = True, **options: Any):
        noisy = float(options.pop("noisy_tv", 0.0))
        for key in ("area", "view", "size"):
            if isinstance(options.get(key), (int, str)):
                options[key] = tuple(int(v) for v in str(options[key]).split("x"))  # "64x64" or 64
        env = CrafterEnv(reward=ENV_IDS[env_id], render_text=render_text, **options)
        if noisy:  # paper Table 4's noisy TV on the picture
            from illm_tools.envs.noisy_tv import NoisyTV

            return NoisyTV(env, noisy)
        return env

    def obs_spec(self, env_id: str) -> ObsSpec:
        return ObsSpec(shape=(64, 64, 3), dtype="uint8", kind="image",
                       description="the 64x64 RGB picture (local view and inventory)")

    def episode_info(self, info: dict) -> dict:
        return {"achievements": info.get("achievements") or {}}

    def episode_metrics(self, episodes: Sequence[EpisodeStats]) -> dict[str, float]:
        from illm_tools.envs.crafter_text import achievement_success_rates, crafter_score

        if not episodes:
            return {"success_rate": float("nan"), "score": float("nan")}
        rates = achievement_success_rates([e.info.get("achievements", {}) for e in episodes])
        return {"success_rate": float("nan"), "score": crafter_score({k: 100 * v for k, v in rates.items()}),
                **{f"achievement_{k}": v for k, v in rates.items()}}


SUITE = CrafterSuite()
