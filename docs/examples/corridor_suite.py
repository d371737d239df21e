"""A fifth environment suite as an illm plug-in: `illm collect --env Corridor-Walk-v0`, `illm train ...`.

One file: the environment (a gymnasium.Env whose info carries the text the LLM reads, the mission
and the valid actions) and its `Suite` (its ids, how to make one, what the policy sees, its text
renderer's name and version, its options). The env pool, the trainer, every bonus and the annotator
take it from there. tests/test_docs_examples.py collects, annotates and trains on it.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from illm_tools.envs.suite import ObsSpec, Suite

ENV_ID = "Corridor-Walk-v0"


class Corridor(gym.Env):
    """`length` cells in a row; "go right" from the last but one reaches the goal (reward 1). The policy
    sees a 7x7x3 grid of MiniGrid codes with the agent as a key (code 5) in column 3."""

    def __init__(self, length: int = 5, render_text: bool = True):
        self.length, self.render_text = int(length), render_text
        self.action_names = ("go left", "go right")
        self.action_space = gym.spaces.Discrete(2)
        self.observation_space = gym.spaces.Box(0, 10, (7, 7, 3), np.uint8)

    def _obs(self):
        grid = np.ones((7, 7, 3), np.uint8)
        grid[self.pos, 3, 0] = 5
        return grid

    def _info(self, info):
        text = f"You are {self.length - 1 - self.pos} steps from the goal" if self.render_text else ""
        info.update(text=text, mission="reach the end of the corridor", valid_actions=list(self.action_names))
        return info

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = int(self.np_random.integers(0, self.length - 1))
        return self._obs(), self._info({})

    def step(self, action):
        self.pos = max(0, self.pos + (1 if int(action) == 1 else -1))
        done = self.pos >= self.length - 1
        return self._obs(), float(done), done, False, self._info({"success": True} if done else {})


class CorridorSuite(Suite):
    name = "corridor"
    renderer = "corridor-text@1"  # part of every cache key: bump the version when the text changes
    description = "a corridor to walk to its end"

    def env_ids(self):
        return [ENV_ID]

    def options(self, env_id):
        return ("length",)  # --env-option length=7; any other option is refused in one line

    def make(self, env_id, *, action_space, render_text=True, **options):
        return Corridor(render_text=render_text, **options)

    def obs_spec(self, env_id):
        return ObsSpec(shape=(7, 7, 3), dtype="uint8", kind="grid", description="the corridor as MiniGrid codes")


SUITE = CorridorSuite()
