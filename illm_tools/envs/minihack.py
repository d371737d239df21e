"""MiniHack (Samvelyan et al. 2021, on the NetHack Learning Environment): the glyphs around the
agent and the game message for the policy, a text written by illm for the LLM.

Env ids: every `MiniHack-*` id minihack registers. The paper's five tasks (Appendix C.2) map to
the ids in `illm_tools.envs.minihack_text.TASKS`. The policy sees a flat int16 array: the 9x9
glyph crop centred on the agent (glyph ids 0..5975) followed by the 256 bytes of the message line
(`ObsSpec.parts`), read by network "glyph" (`GlyphNet`). The text (renderer
"minihack-text@<version>", `minihack_text.render_text`) describes the message, what is near the
agent with direction and distance, and the inventory; the actions get readable names. Success: the
episode ends with NetHack's status TASK_SUCCESSFUL (MiniHack's reward for the goal); the score is
the success rate. `--env-option`s go to `gymnasium.make` (e.g. max_episode_steps, or MiniHack's reward
options: `--env-option reward_lose=-1` makes an episode that ends without success, by a death or the step
limit, cost what a success pays); the moon phase
is fixed (`fix_moon_phase`, else the first message depends on the date). Every episode is seeded:
NetHack's RNGs (without its reseeding) and, for MultiRoom, the MiniGrid level generator.
"""
from __future__ import annotations

import functools
import warnings
from typing import Any

import gymnasium as gym
import numpy as np

from illm_tools.envs.suite import ObsSpec, Suite, gym_options, native_quiet

CROP = (9, 9)
MESSAGE = 256
POLICY_KEYS = ("glyphs_crop", "message")
REWARD_OPTIONS = ("reward_win", "reward_lose", "penalty_step", "penalty_time", "penalty_mode")
"""MiniHack's reward options (`minihack.MiniHack.__init__`): what a success pays (1), an episode ending
otherwise, by a death or the step limit (0), a frozen step (-0.01) and time, which every task takes as
`--env-option`s though its own class names them not."""
TASK_SUCCESSFUL = 2
"""NLE's StepStatus.TASK_SUCCESSFUL (`info["end_status"]`)."""


def _import_minihack() -> None:
    with warnings.catch_warnings(), native_quiet():  # pkg_resources deprecation, NetHack's start-up
        warnings.simplefilter("ignore")
        import minihack  # noqa: F401  (registers the ids)


@functools.lru_cache(maxsize=1)
def env_ids() -> list[str]:
    """The MiniHack-* ids minihack registers."""
    _import_minihack()
    return sorted(k for k in gym.registry if k.startswith("MiniHack-"))


class MiniHackTextEnv(gym.Wrapper):
    """A MiniHack env whose info carries illm's text, mission, readable action names and success."""

    def __init__(self, env: gym.Env, env_id: str, render_text: bool = True):
        from illm_tools.envs import minihack_text
        from illm_tools.envs.minihack_actions import action_names

        super().__init__(env)
        self.render_text = render_text
        self.mission = minihack_text.mission(env_id)
        self.action_names: tuple[str, ...] = action_names(env.unwrapped.actions)
        self._render = minihack_text.render_text

    def _info(self, obs: dict, info: dict) -> dict:
        info["text"] = self._render(obs) if self.render_text else ""
        info["mission"] = self.mission
        info["valid_actions"] = list(self.action_names)
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._seed(int(seed))
        obs, info = self.env.reset(seed=seed, options=options)
        return obs, self._info(obs, info)

    def _seed(self, seed: int) -> None:
        """Seed the game itself: nle's reset(seed=...) seeds only gymnasium's generator. NetHack's
        core and display RNGs get `seed` with its anti-automation reseeding off; MiniHack's levels
        drawn by a MiniGrid generator (MultiRoom) get it too (minihack's own seed() fails there:
        it calls the `seed` method gymnasium removed)."""
        from nle.env.base import NLE

        game = self.env.unwrapped
        NLE.seed(game, seed, seed, reseed=False)
        grid = getattr(game, "minigrid_env", None)
        if grid is not None:
            grid.reset(seed=seed)

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            info["success"] = int(info.get("end_status", 0)) == TASK_SUCCESSFUL
        return obs, reward, terminated, truncated, self._info(obs, info)


class MiniHackSuite(Suite):
    name = "minihack"
    prefixes = ("MiniHack-",)
    renderer = property(lambda self: _renderer())
    network = "glyph"
    description = "MiniHack tasks (minihack on NLE), glyphs and message; text written by illm"

    def env_ids(self) -> list[str]:
        return env_ids()

    def options(self, env_id: str) -> tuple[str, ...]:
        """`gymnasium.make`'s options of the task's class, and the reward options every task hands on to
        MiniHack's base class through its `**kwargs` (`REWARD_OPTIONS`)."""
        return tuple(sorted({*(o for o in gym_options(env_id) if o != "observation_keys"), *REWARD_OPTIONS}))

    def make(self, env_id: str, *, action_space: str, render_text: bool = True, **options: Any) -> MiniHackTextEnv:
        from illm_tools.envs.minihack_text import OBS_KEYS

        _import_minihack()
        keys = tuple(dict.fromkeys((*OBS_KEYS, *POLICY_KEYS)))
        options.setdefault("fix_moon_phase", True)  # else the first message depends on today's date
        with native_quiet():
            env = gym.make(env_id, observation_keys=keys, **options)
        return MiniHackTextEnv(env, env_id, render_text=render_text)

    def obs_spec(self, env_id: str) -> ObsSpec:
        return ObsSpec(shape=(CROP[0] * CROP[1] + MESSAGE,), dtype="int16", kind="glyphs",
                       description="the 9x9 glyph crop around the agent and the 256-byte message",
                       parts={"glyphs_crop": CROP, "message": (MESSAGE,)})

    def policy_obs(self, obs: dict) -> np.ndarray:
        return np.concatenate([obs["glyphs_crop"].reshape(-1).astype(np.int16),
                               obs["message"].astype(np.int16)])


def _renderer() -> str:
    from illm_tools.envs.minihack_text import RENDERER_NAME, RENDERER_VERSION

    return f"{RENDERER_NAME}@{RENDERER_VERSION}"


SUITE = MiniHackSuite()
