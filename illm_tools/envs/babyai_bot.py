"""minigrid's BabyAI expert bot as a collection policy (`illm collect --policy bot`): the states an
expert visits, with a share of random actions so states off its path are logged too.

One `BabyAIBot` per env of an in-process (sync) pool, made at each episode's first step from the
env itself (the bot reads the grid; the rows logged are still the text the agent sees). With
probability `epsilon` an action is uniformly random instead of the bot's; the bot is told the action
actually taken and replans from it (as `illm probe` plays). Where the bot gives up (it asserts on
some states a random action led to), the rest of that episode is random. The bot's "done" (mission
accomplished) is no valid action: a random one is taken there.
"""

from __future__ import annotations

import numpy as np

from illm_tools.errors import UsageError


class BotPolicy:
    """The BabyAI bot in each env of a pool, with `epsilon` random actions (module docstring)."""

    name = "bot"

    def __init__(self, pool, epsilon: float, seed: int):
        from minigrid.core.actions import Actions

        from illm_tools.envs.babyai import _MINIGRID_ACTION

        if pool.suite.name != "babyai" or not pool.env_id.startswith("BabyAI-"):
            raise UsageError(f"--policy bot plays minigrid's BabyAI bot, which solves BabyAI-* levels, not "
                             f"{pool.env_id}: use --policy random")
        if pool.vector != "sync":
            raise UsageError("--policy bot reads each env's grid, so the envs must run in this process: add "
                             "--vector sync")
        self.envs = [env.unwrapped for env in pool.envs.envs]
        self.to_minigrid = [_MINIGRID_ACTION[n] for n in pool.action_names]
        self.done = Actions.done
        self.epsilon = float(epsilon)
        self.rng = np.random.default_rng(seed)
        self.bots: list = [None] * len(self.envs)
        self.taken: list = [None] * len(self.envs)
        self.failed = [False] * len(self.envs)
        self.failures = 0
        """Episodes the bot gave up on (played on at random)."""

    def act(self, obs) -> np.ndarray:
        from minigrid.utils.baby_ai_bot import BabyAIBot

        actions = np.zeros(len(self.envs), dtype=np.int64)
        for i, env in enumerate(self.envs):
            if obs.steps[i] == 0:  # a new episode: a new bot over the fresh grid
                self.bots[i], self.taken[i], self.failed[i] = BabyAIBot(env), None, False
            wanted = None
            if not self.failed[i]:
                try:
                    wanted = self.bots[i].replan(self.taken[i])
                except Exception:  # noqa: BLE001 - the bot asserts on some states; random from here on
                    self.failed[i] = True
                    self.failures += 1
            choices = [a for a, m in enumerate(self.to_minigrid) if m == wanted and m != self.done]
            if choices and self.rng.random() >= self.epsilon:
                actions[i] = choices[0]
            else:
                actions[i] = int(self.rng.integers(len(self.to_minigrid)))
            self.taken[i] = self.to_minigrid[actions[i]]
        return actions


def bot_policy(config, pool) -> BotPolicy:
    """`illm collect --policy bot` (the collect stage's `POLICIES`): the bot with --bot-epsilon random actions."""
    return BotPolicy(pool, config.bot_epsilon, config.seed)
