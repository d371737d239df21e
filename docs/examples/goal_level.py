"""A new level of the BabyAI/MiniGrid family as an illm plug-in: `illm collect --env MiniGrid-GoalCorner-v0`.

One file: the level (a MiniGrid env: a walled room with the goal square in one of its corners) and a
suite that owns its id (`SUITE`: the babyai suite narrowed to this one id, so the level gets the
BabyAI-Text renderer, the grid policy, the action spaces and the oracle unchanged). The level is
registered with gymnasium by the suite, the first time illm asks it for its ids: illm asks the babyai
suite first, whose one listing of the `MiniGrid-` ids a process has then been taken without it, so
this suite, and no other, owns the id. tests/test_example_level.py collects, annotates (with the
oracle) and trains on it.
"""

from __future__ import annotations

import gymnasium as gym
from minigrid.core.grid import Grid
from minigrid.core.mission import MissionSpace
from minigrid.core.world_object import Goal
from minigrid.minigrid_env import MiniGridEnv

from illm_tools.envs.babyai import BabyAISuite

ENV_ID = "MiniGrid-GoalCorner-v0"  # "MiniGrid-": the game the prompts name, and one the oracle knows
MISSION = "get to the green goal square"  # a mission the oracle's planner reads (MiniGrid's own wording)


class GoalCorner(MiniGridEnv):
    """A square room of `size` cells a side (walls included); the goal in one of its four corners,
    the agent anywhere else. MiniGrid pays 1 - 0.9 * steps / max_steps on reaching the goal."""

    def __init__(self, size: int = 7, max_steps: int | None = None, **kwargs):
        super().__init__(mission_space=MissionSpace(mission_func=lambda: MISSION), grid_size=size,
                         max_steps=max_steps or 4 * size * size, see_through_walls=True, **kwargs)

    def _gen_grid(self, width: int, height: int) -> None:
        self.grid = Grid(width, height)
        self.grid.wall_rect(0, 0, width, height)
        corners = [(1, 1), (width - 2, 1), (1, height - 2), (width - 2, height - 2)]
        self.put_obj(Goal(), *corners[self._rand_int(0, len(corners))])
        self.place_agent()
        self.mission = MISSION


def register() -> None:
    """Register the level with gymnasium (once: a second call changes nothing)."""
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point=f"{__name__}:GoalCorner")


class GoalCornerSuite(BabyAISuite):
    """The babyai suite for this level alone: its text, renderer, observation, network, action spaces
    and options are the babyai suite's."""

    name = "goal-corner"
    prefixes = (ENV_ID,)
    description = "a MiniGrid room with the goal in a corner (BabyAI-Text)"

    def env_ids(self) -> list[str]:
        register()  # illm asks this suite only after the babyai suite has listed its ids
        return [ENV_ID]


SUITE = GoalCornerSuite()
