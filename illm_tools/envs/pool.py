"""EnvPool: N environments of one id stepped together through gymnasium's vector envs, with
same-step autoreset, deterministic episode seeds and per-episode statistics. This is the only
place that decides episode seeds.

Stepping is gymnasium's: `SyncVectorEnv` (all envs in this process) or `AsyncVectorEnv` (one
process each, for suites whose envs step slowly: Crafter), both with
`AutoresetMode.SAME_STEP`: when env i finishes at a step, that step's `PoolStep.obs` already holds
the first state of env i's next episode; the step's reward/terminated/truncated and its
`EpisodeStats` belong to the finished episode. What this file adds is small:
- `EpisodeSeeds`, a wrapper that reseeds every episode: env i's k-th episode (k = 0, 1, ...) is
  reset with seed `seed + i + k * num_envs`, so the pool's episodes use the distinct seeds seed,
  seed + 1, ..., and every episode's seed depends only on (seed, num_envs, i, k), never on which
  env finished first (gymnasium's vector envs seed only the first reset). Given a list of
  `episode_seeds`, episode k of env i takes `episode_seeds[(i + k * num_envs) % len]` instead: a
  fixed set of layouts (one seed: one MultiRoom map, as in paper Figure 1's heatmap);
- `PolicyObservation`, a wrapper giving the suite's policy array as the observation (the vector
  env batches it), the env's own observation staying in the suite's hands;
- the bookkeeping of episode returns, lengths and the suite's success and extras.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np

from illm_tools.envs import make_env, resolve_action_space, suite_of
from illm_tools.envs.suite import EpisodeStats, check_options
from illm_tools.errors import UsageError

__all__ = ["EnvPool", "EpisodeStats", "PoolObs", "PoolStep"]

VECTOR_MODES = ("auto", "sync", "async")


@dataclass
class PoolObs:
    """The current state of every env of the pool."""

    images: np.ndarray
    """[N, ...] the suite's policy array (`Suite.obs_spec`: MiniGrid's (7, 7, 3) codes, Atari's
    (4, 84, 84) frames, ...)."""
    texts: list[str]
    """The rendered observation of each env ("" when the pool was made with render=False, or the
    suite has no text)."""
    missions: list[str]
    seeds: np.ndarray
    """int64 [N]: the seed of each env's current episode."""
    steps: np.ndarray
    """int64 [N]: the index of this state in its episode (0 right after a reset)."""
    positions: np.ndarray | None = None
    """int64 [N, 2]: the agent's (x, y) cell where the env reports it (MiniGrid), else None."""


@dataclass
class PoolStep:
    """What one `EnvPool.step` returns."""

    rewards: np.ndarray
    """float32 [N]."""
    terminated: np.ndarray
    """bool [N]."""
    truncated: np.ndarray
    """bool [N]."""
    obs: PoolObs
    """The next state; for envs that finished this step, the first state of their new episode."""
    episodes: list[EpisodeStats]
    """The episodes that finished this step, by env index."""


class EpisodeSeeds(gym.Wrapper):
    """Reset k (k = 0, 1, ...) of env `index` of `num_envs` uses seed `base + index + k * num_envs`,
    whatever seed the caller passes; `info["episode_seed"]` says which."""

    def __init__(self, env: gym.Env, base: int, index: int, num_envs: int, cycle: tuple[int, ...] = ()):
        super().__init__(env)
        self.base, self.index, self.num_envs, self.episodes = base, index, num_envs, 0
        self.cycle = tuple(cycle)
        """Seeds to cycle through instead (a fixed set of layouts); empty: a new seed each episode."""

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        k = self.index + self.episodes * self.num_envs
        seed = self.cycle[k % len(self.cycle)] if self.cycle else self.base + k
        self.episodes += 1
        obs, info = self.env.reset(seed=seed, options=options)
        info["episode_seed"] = seed
        return obs, info


class PolicyObservation(gym.ObservationWrapper):
    """The suite's policy array as the observation (`Suite.policy_obs`)."""

    def __init__(self, env: gym.Env, suite, example: np.ndarray):
        super().__init__(env)
        self.suite = suite
        info = np.iinfo(example.dtype) if np.issubdtype(example.dtype, np.integer) else np.finfo(example.dtype)
        self.observation_space = gym.spaces.Box(info.min, info.max, example.shape, example.dtype)

    def observation(self, observation: Any) -> np.ndarray:
        return self.suite.policy_obs(observation)


def _make_one(env_id: str, index: int, base: int, num_envs: int, render: bool, action_space: str,
              options: dict, cycle: tuple[int, ...] = ()) -> gym.Env:
    """Env `index` of a pool (module-level so AsyncVectorEnv can pickle it into its workers)."""
    suite = suite_of(env_id)
    env = make_env(env_id, render_text=render, action_space=action_space, **options)
    example = suite.policy_obs(env.observation_space.sample())
    return EpisodeSeeds(PolicyObservation(env, suite, example), base, index, num_envs, cycle)


def _take(info: dict, key: str, i: int, default: Any = None) -> Any:
    """Env i's value of `key` in a vector env's info (present where the mask `_key` says so; a
    dict value, such as Crafter's achievements, is batched key by key and comes back whole)."""
    if key not in info or not info.get(f"_{key}", np.ones(i + 1, bool))[i]:
        return default
    value = info[key]
    if isinstance(value, dict):
        return {k: _take(value, k, i) for k in value if not k.startswith("_")}
    return value[i]


class EnvPool:
    """N environments of one id, stepped together (see the module docstring)."""

    def __init__(self, env_id: str, num_envs: int, seed: int, *, render: bool = True, vector: str = "auto",
                 episode_seeds: tuple[int, ...] = (), **options: Any):
        if num_envs <= 0:
            raise UsageError(f"num_envs must be positive, got {num_envs}")
        if vector not in VECTOR_MODES:
            raise UsageError(f"--vector must be one of {', '.join(VECTOR_MODES)}, got {vector!r}")
        self.env_id = env_id
        self.suite = suite_of(env_id)
        self.num_envs = int(num_envs)
        self.seed = int(seed)
        self.episode_seeds = tuple(int(s) for s in episode_seeds)
        """Seeds the episodes cycle through (a fixed set of layouts); empty: seed + i + k * num_envs."""
        self.render = render and self.suite.renderer is not None
        # the resolved action space ("auto" never appears here): what a run or dataset records
        self.action_space_name = resolve_action_space(env_id, options.pop("action_space", "auto"))
        options = {k: v for k, v in options.items() if not (k == "num_dists" and v is None)}
        check_options(env_id, options, self.suite.options(env_id))  # here, not in an async worker
        fns = [partial(_make_one, env_id, i, self.seed, self.num_envs, self.render, self.action_space_name, options,
                       self.episode_seeds) for i in range(self.num_envs)]
        mode = self.suite.vector if vector == "auto" else vector
        same_step = gym.vector.AutoresetMode.SAME_STEP
        if mode == "async" and self.num_envs > 1:
            self.vector = "async"
            self.envs = gym.vector.AsyncVectorEnv(fns, autoreset_mode=same_step, context="spawn")
        else:
            self.vector = "sync"
            self.envs = gym.vector.SyncVectorEnv(fns, autoreset_mode=same_step)
        self.action_names: tuple[str, ...] = tuple(self.envs.get_attr("action_names")[0])
        n = self.num_envs
        self._seeds = np.zeros(n, dtype=np.int64)
        self._steps = np.zeros(n, dtype=np.int64)
        self._returns = np.zeros(n, dtype=np.float64)
        self._started = False

    def episode_seed(self, env_index: int, episode_index: int) -> int:
        """The seed of env `env_index`'s `episode_index`-th episode (see the module docstring)."""
        k = env_index + episode_index * self.num_envs
        return self.episode_seeds[k % len(self.episode_seeds)] if self.episode_seeds else self.seed + k

    def _obs(self, images: np.ndarray, info: dict) -> PoolObs:
        n = self.num_envs
        for i in range(n):
            seed = _take(info, "episode_seed", i)
            if seed is not None:  # a new episode began in env i
                self._seeds[i], self._steps[i], self._returns[i] = seed, 0, 0.0
        texts = info.get("text")
        positions = info.get("agent_pos")
        return PoolObs(images=images, texts=[str(t) for t in texts] if texts is not None else [""] * n,
                       missions=[str(m) for m in info["mission"]], seeds=self._seeds.copy(),
                       steps=self._steps.copy(),
                       positions=np.asarray(positions, dtype=np.int64).reshape(n, 2) if positions is not None else None)

    def reset(self) -> PoolObs:
        """Start every env on its first episode (seeds seed .. seed + num_envs - 1)."""
        if self._started:  # the episode counters restart too: a reset pool repeats its episodes
            self.envs.call("__setattr__", "episodes", 0)
        self._started = True
        images, info = self.envs.reset()
        return self._obs(images, info)

    def step(self, actions: np.ndarray) -> PoolStep:
        """Apply one action index per env; finished envs are reset within this call."""
        if not self._started:
            raise UsageError("EnvPool.step called before reset()")
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,):
            raise UsageError(f"expected {self.num_envs} actions, got an array of shape {actions.shape}")
        if actions.size and (actions.min() < 0 or actions.max() >= len(self.action_names)):
            raise UsageError(f"actions must be in 0..{len(self.action_names) - 1} "
                             f"({', '.join(self.action_names)}), got {actions.tolist()}")
        images, rewards, terminated, truncated, info = self.envs.step(actions)
        self._steps += 1
        self._returns += rewards
        episodes: list[EpisodeStats] = []
        final = info.get("final_info", {})
        for i in np.flatnonzero(np.logical_or(terminated, truncated)):
            last = {k: _take(final, k, i) for k in final if not k.startswith("_")}
            episodes.append(EpisodeStats(int(i), float(self._returns[i]), int(self._steps[i]),
                                         None if last.get("success") is None else bool(last["success"]),
                                         self.suite.episode_info(last)))
        return PoolStep(np.asarray(rewards, dtype=np.float32), np.asarray(terminated, dtype=bool),
                        np.asarray(truncated, dtype=bool), self._obs(images, info), episodes)

    def close(self) -> None:
        self.envs.close()
