"""The `Suite` contract: one family of environments and everything illm needs to know about it.

A suite answers, for each of its env ids:
- which ids it owns (`env_ids`, `owns`) and how to make one (`make`; its own options pass through
  `--env-option KEY=VALUE` to it and to no other suite);
- what the policy sees (`obs_spec`: shape, dtype and kind of one observation array, turned out of
  the env's own observation by `policy_obs`), what a trajectory keeps of it (`raw_obs`), how
  tensors are made of it (`observation`: the adapter the torso and the bonuses read it through), and
  which policy network reads it (`network`, a plain name the rl layer resolves, e.g. "grid-mission";
  a plug-in may give its own class as "module:Class");
- its text: `renderer` ("name@version", part of every annotation cache key; None when the suite
  has no text observation, e.g. Atari), with `info["text"]` and `info["mission"]` set by `make`'s
  env after every reset and step, and `info["valid_actions"]` its readable action names;
- how an episode counts: `info["success"]` (True / False, or None where the suite has no success)
  on an episode's last step, the extras `episode_info` keeps of that step's info (Crafter's
  achievements), and `episode_metrics`, the per-update figures the trainer logs, among them
  `score` (the suite's headline number, named by `score_name`);
- its action vocabularies (`action_spaces`, `default_action_space`) and whether its envs step fast
  enough to share one process (`vector`: "sync") or are better each in their own ("async").
"""
from __future__ import annotations

import contextlib
import inspect
import os
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from illm_tools.errors import UsageError


@dataclass(frozen=True)
class ObsSpec:
    """One observation as the policy (and every exploration bonus) sees it."""

    shape: tuple[int, ...]
    dtype: str
    """numpy dtype name of the array, e.g. "uint8", "int16"."""
    kind: str
    """How to read it: "grid" (MiniGrid's (H, W, 3) object/colour/state codes), "frames" (stacked
    grey frames, (C, H, W) uint8), "image" (an RGB picture, (H, W, 3) uint8), "glyphs" (MiniHack:
    a flat int16 array, the glyph crop then the message bytes; `parts` gives the split)."""
    description: str
    """What it is, in words, for the README and `illm envs`."""
    parts: dict[str, tuple[int, ...]] = field(default_factory=dict)
    """For packed kinds: the named pieces of the flat array, in order, with their shapes."""


class EpisodeStats(NamedTuple):
    """One finished episode."""

    env_index: int
    episode_return: float
    length: int
    success: bool | None
    """The suite's success (BabyAI, MiniHack: the task solved); None where the suite has none."""
    info: dict = {}
    """What the suite keeps of the episode's last info (`Suite.episode_info`, e.g. achievements)."""


def mean_or_nan(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


@contextlib.contextmanager
def native_quiet() -> Iterator[None]:
    """Silence what native code writes straight to file descriptors 1 and 2 (the Arcade Learning
    Environment's banner, NetHack's start-up lines): Python's redirect_stdout cannot reach them."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


def gym_options(env_id: str) -> tuple[str, ...]:
    """The keyword options `gymnasium.make(env_id, ...)` takes: its env class's constructor
    parameters and `max_episode_steps`."""
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    entry = gym.spec(env_id).entry_point
    creator = load_env_creator(entry) if isinstance(entry, str) else entry
    params = inspect.signature(creator).parameters.values()
    return ("max_episode_steps", *sorted(p.name for p in params
                                         if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL) and p.name != "self"))


def check_options(env_id: str, options: dict, allowed: Sequence[str]) -> None:
    """Refuse in one line the `--env-option`s this env does not take, naming those it does."""
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise UsageError(f"{env_id} takes no env option {', '.join(unknown)}; it takes "
                         f"{', '.join(sorted(set(allowed))) or 'none'}")


class Suite:
    """Base class of a suite; subclasses set the attributes and override what differs."""

    name: str = ""
    prefixes: tuple[str, ...] = ()
    """Env ids of the suite start with one of these (a cheap test before `env_ids()`); () : any."""
    renderer: str | None = None
    """"<renderer name>@<version>", or None: no text observation."""
    score_name: str = "success rate"
    """What `episode_metrics()["score"]` is, for tables."""
    vector: str = "sync"
    """"sync" (envs stepped in this process) or "async" (one process each: slow envs)."""
    network: str = "grid-mission"
    """The policy network for this suite's observations, by name: "grid-mission" (MiniGrid's grid and
    mission), "frame" (pictures: stacked frames or RGB), "glyph" (MiniHack's glyphs and message), or
    another name the rl layer's network table knows; a plug-in may give its own class as
    "module:Class" instead."""
    description: str = ""
    """One line on the suite for the README and `illm envs`."""

    # --- ids ---------------------------------------------------------------------------------
    def env_ids(self) -> list[str]:
        raise NotImplementedError

    def owns(self, env_id: str) -> bool:
        return env_id.startswith(self.prefixes or ("",)) and env_id in self.env_ids()

    # --- making one ---------------------------------------------------------------------------
    def make(self, env_id: str, *, action_space: str, render_text: bool = True, **options: Any):
        """The env: a gymnasium.Env whose info carries text, mission, valid_actions every step and
        success (+ the `episode_info` extras) on the last step of an episode."""
        raise NotImplementedError

    def options(self, env_id: str) -> tuple[str, ...]:
        """The `--env-option` names this env takes (`make` refuses the others)."""
        return gym_options(env_id)

    def action_spaces(self, env_id: str) -> tuple[str, ...]:
        """Named action vocabularies this env offers (the first is the default)."""
        return ("default",)

    def default_action_space(self, env_id: str) -> str:
        return self.action_spaces(env_id)[0]

    # --- observations -------------------------------------------------------------------------
    def obs_spec(self, env_id: str) -> ObsSpec:
        raise NotImplementedError

    def observation(self, env_id: str):
        """The observation adapter of this env (`illm_tools.envs.observations`): how the policy's
        torso and the bonuses read its arrays. Default: the adapter registered for `obs_spec`'s
        kind; a suite with a kind of its own returns its own `Observation` here."""
        from illm_tools.envs.observations import observation_of

        return observation_of(self.obs_spec(env_id))

    def mission_vocab(self, max_len: int):
        """How the policy reads this suite's missions: word ids of at most `max_len` words
        (`MissionVocab`; default BabyAI's instruction grammar, any other word one unknown id)."""
        from illm_tools.envs.encoding import MissionVocab

        return MissionVocab(max_len)

    def policy_obs(self, obs: Any) -> np.ndarray:
        """The policy's array from one observation of `make`'s env."""
        return obs

    def raw_obs(self, array: np.ndarray) -> np.ndarray:
        """What a trajectory row keeps of one policy array (default: all of it)."""
        return array

    def hop_frame(self, raw: np.ndarray) -> np.ndarray:
        """What iLLM(hop)'s Hopfield translation reads of a raw observation (`raw_obs`): the paper's
        grey-scaled observation (B.1); default the raw observation itself (symbolic grids and glyphs
        have no colour channels; Atari's frames are grey already)."""
        return raw

    def hop_input(self, array: np.ndarray) -> np.ndarray:
        """`hop_frame` of one policy array (the trainer's and evaluator's path)."""
        return self.hop_frame(self.raw_obs(array))

    # --- episodes -----------------------------------------------------------------------------
    def episode_info(self, info: dict) -> dict:
        """What to keep of an episode's last info for `episode_metrics` (default: nothing)."""
        return {}

    def episode_metrics(self, episodes: Sequence[EpisodeStats]) -> dict[str, float]:
        """Per-update figures of the episodes that ended in it: `success_rate` (NaN when none ended)
        and `score`, here the success rate."""
        rate = mean_or_nan([float(e.success) for e in episodes if e.success is not None])
        return {"success_rate": rate, "score": rate}
