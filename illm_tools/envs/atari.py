"""Atari 2600 games through ale-py, with the standard preprocessing; no text observation.

Env ids: the `ALE/<Game>-v5` ids ale-py registers (the paper's MontezumaRevenge, PrivateEye,
Gravitar, Pitfall and Seaquest among them). The v5 settings stay (sticky actions with probability
0.25, the minimal action set, at most 108,000 frames an episode) and gymnasium's wrappers add the
preprocessing of Mnih et al. (2015) as Machado et al. (2018) recommend for v5: `AtariPreprocessing`
(up to 30 no-op actions at reset, frame skip 4 with the max over the last two frames, grey, 84x84;
no episode end on a lost life) and `FrameStackObservation` (the last 4 frames). The policy sees
the (4, 84, 84) uint8 stack through the Nature CNN (network "frame", `FrameNet`); a
trajectory keeps the newest frame only (84 x 84 bytes a row). The score is the mean episode
return (the game's own points); there is no success.

`--env-option noisy_tv=<rho>`: the noisy TV of paper Table 4 (`illm_tools.envs.noisy_tv`) on each
frame before stacking.

Atari has no text: `info["text"]` and `info["mission"]` are empty, `renderer_of` refuses it, and
`illm annotate` on an Atari dataset says so. ppo, rnd, ngu and apt train on it; iLLM on images
needs the Hopfield translation (`--mode hop`, a later issue).
"""
from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from illm_tools.envs.suite import EpisodeStats, ObsSpec, Suite, mean_or_nan, native_quiet
from illm_tools.errors import UsageError

PREPROCESSING = ("noop_max", "terminal_on_life_loss", "frame_stack", "noisy_tv")
"""Options of the preprocessing (the rest of `--env-option` goes to the ALE env: repeat_action_probability,
full_action_space, max_num_frames_per_episode, mode, difficulty)."""
ALE_OPTIONS = ("repeat_action_probability", "full_action_space", "max_num_frames_per_episode", "mode",
               "difficulty")


@functools.lru_cache(maxsize=1)
def env_ids() -> list[str]:
    """The ALE/<Game>-v5 ids ale-py registers."""
    import ale_py

    gym.register_envs(ale_py)
    return sorted(k for k in gym.registry if k.startswith("ALE/") and k.endswith("-v5"))


class AtariInfo(gym.Wrapper):
    """Adds illm's info keys: empty text and mission, the readable action names, success None at an
    episode's end."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        meanings = env.unwrapped.get_action_meanings()
        self.action_names: tuple[str, ...] = tuple(m.lower().replace("upright", "up right")
                                                   .replace("upleft", "up left").replace("downright", "down right")
                                                   .replace("downleft", "down left").replace("fire", " fire")
                                                   .replace("  ", " ").strip() for m in meanings)

    def _info(self, info: dict) -> dict:
        info.update(text="", mission="", valid_actions=list(self.action_names))
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return obs, self._info(info)

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            info["success"] = None
        return obs, reward, terminated, truncated, self._info(info)


def make_atari(env_id: str, *, noop_max: int = 30, terminal_on_life_loss: bool = False, frame_stack: int = 4,
               noisy_tv: float = 0.0, **options: Any) -> AtariInfo:
    """gym.make(env_id) with the preprocessing of the module docstring."""
    from gymnasium.wrappers import AtariPreprocessing, FrameStackObservation

    if int(frame_stack) < 1:
        raise UsageError(f"frame_stack must be at least 1, got {frame_stack}")
    with native_quiet():  # the ALE prints its banner on the first load
        env = gym.make(env_id, frameskip=1, **options)
    env = AtariPreprocessing(env, noop_max=int(noop_max), frame_skip=4, screen_size=84, grayscale_obs=True,
                             terminal_on_life_loss=bool(terminal_on_life_loss))
    if float(noisy_tv):  # each new frame, before stacking (paper Table 4)
        from illm_tools.envs.noisy_tv import NoisyTV

        env = NoisyTV(env, float(noisy_tv))
    return AtariInfo(FrameStackObservation(env, int(frame_stack)))


class AtariSuite(Suite):
    name = "atari"
    prefixes = ("ALE/",)
    renderer = None
    score_name = "mean return"
    network = "frame"
    description = "Atari 2600 games (ale-py v5), grey 84x84 frames, no text"

    def env_ids(self) -> list[str]:
        return env_ids()

    def options(self, env_id: str) -> tuple[str, ...]:
        return (*PREPROCESSING, *ALE_OPTIONS)

    def make(self, env_id: str, *, action_space: str, render_text: bool = True, **options: Any) -> AtariInfo:
        return make_atari(env_id, **options)

    def action_spaces(self, env_id: str) -> tuple[str, ...]:
        return ("minimal",)  # the game's minimal set (`--env-option full_action_space=true`: all 18)

    def obs_spec(self, env_id: str) -> ObsSpec:
        return ObsSpec(shape=(4, 84, 84), dtype="uint8", kind="frames",
                       description="the last 4 grey 84x84 frames (frame skip 4, sticky actions 0.25)")

    def raw_obs(self, array: np.ndarray) -> np.ndarray:
        return array[-1]

    def episode_metrics(self, episodes: Sequence[EpisodeStats]) -> dict[str, float]:
        return {"success_rate": float("nan"), "score": mean_or_nan([e.episode_return for e in episodes])}


SUITE = AtariSuite()
