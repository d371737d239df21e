"""EnvPool: N text environments stepped in one process, with same-step autoreset and per-episode
statistics. This is the only place that decides episode seeds.

Same-step autoreset: when env i finishes at a step, that step's `PoolStep.obs` already holds the
first state of env i's next episode (gymnasium's vector envs instead return the last state and
reset one step later). The step's reward/terminated/truncated belong to the finished episode.

Episode seeds: env i's k-th episode (k = 0, 1, ...) is reset with seed `seed + i + k * num_envs`.
The pool's episodes therefore use the distinct seeds seed, seed + 1, seed + 2, ..., and the seed of
every episode depends only on (seed, num_envs, i, k), never on which env finished first.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from illm_tools.envs import make_env, resolve_action_space
from illm_tools.errors import UsageError


@dataclass
class PoolObs:
    """The current state of every env of the pool."""

    images: np.ndarray
    """uint8 [N, 7, 7, 3]: MiniGrid's egocentric (object, colour, state) view."""
    directions: np.ndarray
    """int64 [N]: the agent's absolute direction (0 right, 1 down, 2 left, 3 up)."""
    texts: list[str]
    """The rendered observation of each env ("" when the pool was made with render=False)."""
    missions: list[str]
    seeds: np.ndarray
    """int64 [N]: the seed of each env's current episode."""
    steps: np.ndarray
    """int64 [N]: the index of this state in its episode (0 right after a reset)."""


class EpisodeStats(NamedTuple):
    """One finished episode; unpacks as (env_index, episode_return, length, success)."""

    env_index: int
    episode_return: float
    length: int
    success: bool
    """Terminated with a positive reward (BabyAI pays reward only on success)."""


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


class EnvPool:
    """N text environments of one id, stepped together in this process."""

    def __init__(self, env_id: str, num_envs: int, seed: int, *, render: bool = True, **options: Any):
        if num_envs <= 0:
            raise UsageError(f"num_envs must be positive, got {num_envs}")
        self.env_id = env_id
        self.num_envs = int(num_envs)
        self.seed = int(seed)
        self.render = render
        # the resolved action space ("auto" never appears here): what a run or dataset records
        self.action_space_name = resolve_action_space(env_id, options.pop("action_space", "auto"))
        self.envs = [make_env(env_id, render_text=render, action_space=self.action_space_name, **options)
                     for _ in range(self.num_envs)]
        self.action_names: tuple[str, ...] = tuple(self.envs[0].action_names)
        n = self.num_envs
        self._episode_index = np.zeros(n, dtype=np.int64)  # k: episodes started by each env
        self._seeds = np.zeros(n, dtype=np.int64)
        self._steps = np.zeros(n, dtype=np.int64)
        self._returns = np.zeros(n, dtype=np.float64)
        self._started = False

    def episode_seed(self, env_index: int, episode_index: int) -> int:
        """The seed of env `env_index`'s `episode_index`-th episode (see the module docstring)."""
        return self.seed + env_index + episode_index * self.num_envs

    def _reset_env(self, i: int) -> tuple[dict, dict]:
        seed = self.episode_seed(i, int(self._episode_index[i]))
        self._episode_index[i] += 1
        self._seeds[i] = seed
        self._steps[i] = 0
        self._returns[i] = 0.0
        return self.envs[i].reset(seed=seed)

    def _obs(self, results: list[tuple[dict, dict]]) -> PoolObs:
        return PoolObs(
            images=np.stack([obs["image"] for obs, _ in results]),
            directions=np.fromiter((obs["direction"] for obs, _ in results), dtype=np.int64, count=self.num_envs),
            texts=[info["text"] for _, info in results],
            missions=[obs["mission"] for obs, _ in results],
            seeds=self._seeds.copy(),
            steps=self._steps.copy(),
        )

    def reset(self) -> PoolObs:
        """Start every env on its first episode (seeds seed .. seed + num_envs - 1)."""
        self._episode_index[:] = 0
        self._started = True
        return self._obs([self._reset_env(i) for i in range(self.num_envs)])

    def step(self, actions: np.ndarray) -> PoolStep:
        """Apply one action index per env; finished envs are reset within this call."""
        if not self._started:
            raise UsageError("EnvPool.step called before reset()")
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,):
            raise UsageError(f"expected {self.num_envs} actions, got an array of shape {actions.shape}")
        n = self.num_envs
        rewards = np.zeros(n, dtype=np.float32)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        episodes: list[EpisodeStats] = []
        results = []
        for i, (env, action) in enumerate(zip(self.envs, actions.tolist())):
            obs, reward, term, trunc, info = env.step(action)
            rewards[i], terminated[i], truncated[i] = reward, term, trunc
            self._steps[i] += 1
            self._returns[i] += reward
            if term or trunc:
                episodes.append(EpisodeStats(i, float(self._returns[i]), int(self._steps[i]),
                                             bool(term and reward > 0)))
                obs, info = self._reset_env(i)
            results.append((obs, info))
        return PoolStep(rewards, terminated, truncated, self._obs(results), episodes)

    def close(self) -> None:
        for env in self.envs:
            env.close()
