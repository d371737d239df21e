"""Crafter (Hafner 2021): an open-ended 2-D survival world; the policy sees its 64x64 picture (or,
with the semantic ids, what the picture shows as cell codes), the LLM a text written by illm, and
the score is Crafter's.

Env ids: `CrafterReward-v1` (the game's reward: +1 for each achievement unlocked for the first
time in an episode, +-0.1 per health point gained or lost) and `CrafterNoReward-v1` (reward 0,
for pure exploration), the ids crafter registers for the old gym API; here they are a gymnasium
env, `CrafterEnv`. `--env-option`s: area, view, size, length (crafter.Env's; length: steps before
an episode is cut, 10,000 by default), noisy_tv (paper Table 4's noise patch, `noisy_tv.py`). An episode ends when the player dies (terminated) or at
`length` (truncated). Each episode is generated from its own seed (the pool's episode seed).

The policy's view: the 64x64 RGB picture by default; `CrafterReward-Semantic-v1` and
`CrafterNoReward-Semantic-v1` are the same games with the semantic view instead (`semantic_view`):
the picture's 9x7 cells as codes (each cell's material and the object drawn on it, the player's
texture giving its facing and sleep), the inventory's 16 counts and the daylight, 143 bytes (kind
"cells", read by network "frame"'s cell torso), and no picture is drawn: drawing it costs 1.00 ms
of a 1.46 ms step, against 0.35 ms a semantic step, on one core of a 2-core Xeon
(docs/results/measured/crafter-env-parts.txt). Their text, score and LLM prompts are the
pixel ids' (a cache key names the game, "Crafter", not the id: both share one annotation cache);
they take the options area and length (the view's shape is fixed; there is no picture for size
or noisy_tv). A view is an env id rather than an option because a suite answers `obs_spec`,
`observation` and `policy_obs` by env id alone: every stage (train, eval, collect, the bonuses'
encoders, hop) then reads the view the run was made with.

The text (renderer "crafter-text@<version>", `crafter_text.render_text`): what the agent faces,
what is in view with direction and distance, the inventory, health/food/drink/energy. The score
(`crafter_text.crafter_score`): the geometric mean of the 22 achievements' success rates over the
episodes, exp(mean ln(1 + s_i)) - 1 with s_i in percent; each achievement's success rate is a
metric too (`achievement_<name>`). There is no success.

Speed: a reset generates a 64x64 world with opensimplex noise, which numba compiles when it is
installed (a project dependency: 0.074 s a reset against 1.095 s in pure Python on that Xeon; 2.7 s
on issue 70's 2-core AVX2 EPYC), the same world bit for bit. crafter also builds its whole 64x64
semantic map into every step's info (0.055 ms), which illm never reads: `CrafterEnv` skips it
(`_no_semantic_map`). The pool steps Crafter's envs in the trainer's process
(`vector = "sync"`): with the world generator compiled, a process per env (gymnasium's
AsyncVectorEnv, 16 of them) cost more in pipes and scheduling than the second core gave back, on a
2-core Xeon beside other work: 16 pixel envs stepped 339 steps/s in one process against 126 in
sixteen (277 against 91 held to one core), the semantic ones 1,005 against 940 (1,023 against 195)
(docs/results/measured/crafter-vector.txt). On a machine with many free cores `--vector async` may
still pay for the pixel view. crafter despawns creatures in set order, which differs between
processes; `CrafterEnv` orders them by position so that a seed gives one world in any process.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from illm_tools.envs.suite import EpisodeStats, ObsSpec, Suite

ENV_IDS = {"CrafterReward-v1": True, "CrafterNoReward-v1": False,
           "CrafterReward-Semantic-v1": True, "CrafterNoReward-Semantic-v1": False}
"""Id -> whether the env pays the game's reward."""
OPTIONS = ("area", "view", "size", "length", "noisy_tv")
SEMANTIC_OPTIONS = ("area", "length")
"""What the semantic ids take: no picture (size, noisy_tv), and the view's shape is the spec's."""
GRID = (9, 7)
"""The picture's local view in cells (x, y): crafter's 9x9 view less the inventory's 2 rows."""
OBJECT_TEXTURES = ("player-left", "player-right", "player-up", "player-down", "player-sleep", "cow", "zombie",
                   "skeleton", "arrow-left", "arrow-right", "arrow-up", "arrow-down", "plant", "plant-ripe", "fence")
"""The textures crafter draws objects with; an object's code is its texture's place here plus one (0:
no object, len + 1: a texture not listed). Append only: the codes are what a trained policy read."""
_OBJECT_CODES = {name: i + 1 for i, name in enumerate(OBJECT_TEXTURES)}
SEMANTIC_PARTS = {"materials": GRID[::-1], "objects": GRID[::-1], "inventory": (16,), "daylight": (1,)}
"""The semantic view's parts, in order (`ObsSpec.parts`): the grids as the picture shows them, rows
north to south; every byte a code below 256."""


def is_semantic(env_id: str) -> bool:
    return env_id.endswith("-Semantic-v1")


def semantic_view(env: Any) -> np.ndarray:
    """What crafter.Env `env`'s picture shows, as uint8 codes, without drawing it (the kind "cells",
    `SEMANTIC_PARTS`): each of the 9x7 cells' material (the world's material id, 0 past the
    world's edge) and the object drawn on it (`OBJECT_TEXTURES`: the player's texture says where it
    faces and whether it sleeps), the inventory's counts in crafter's order (health, food, drink,
    energy, then the items; 0-9), and the daylight in tenths (0-9; the picture darkens at night)."""
    world, player = env._world, env._player
    (w, h), (px, py) = GRID, (int(player.pos[0]), int(player.pos[1]))
    x0, y0 = px - w // 2, py - h // 2
    xs, xe, ys, ye = max(x0, 0), min(x0 + w, world.area[0]), max(y0, 0), min(y0 + h, world.area[1])
    cells = np.zeros((2, w, h), np.uint8)
    cells[0, xs - x0:xe - x0, ys - y0:ye - y0] = world._mat_map[xs:xe, ys:ye]
    index = world._obj_map[xs:xe, ys:ye]
    for i, j in zip(*np.nonzero(index)):
        cells[1, xs - x0 + i, ys - y0 + j] = _OBJECT_CODES.get(world._objects[index[i, j]].texture,
                                                               len(OBJECT_TEXTURES) + 1)
    counts = np.clip(list(player.inventory.values()), 0, 255)
    return np.concatenate([cells.transpose(0, 2, 1).reshape(-1), counts.astype(np.uint8),
                           np.array([round(9 * float(world.daylight))], np.uint8)])


def _no_semantic_map() -> None:
    """Stands in for crafter.Env's `_sem_view`, whose 64x64 map (copied, every object written in)
    crafter puts in each step's info and illm never reads."""
    return None


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

    def __init__(self, reward: bool = True, render_text: bool = True, semantic: bool = False, **options: Any):
        import crafter

        from illm_tools.envs import crafter_text

        self._env = crafter.Env(reward=reward, seed=0, **options)
        _ordered_world(self._env._world)
        self._env._sem_view = _no_semantic_map
        self._text = crafter_text
        self.render_text = render_text
        self.action_names: tuple[str, ...] = crafter_text.ACTION_NAMES
        self.action_space = gym.spaces.Discrete(len(self.action_names))
        if semantic:  # crafter.Env's reset and step return `_obs()`: the codes instead of the picture
            self._env._obs = lambda: semantic_view(self._env)
            size = sum(int(np.prod(shape)) for shape in SEMANTIC_PARTS.values())
            self.observation_space = gym.spaces.Box(0, 255, (size,), np.uint8)
        else:
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
    vector = "sync"  # see the module docstring: on 2 cores the pipes cost more than a second core gives
    network = "frame"
    description = ("Crafter (crafter), 64x64 RGB picture (the -Semantic ids: its cells' codes); text written by illm; "
                   "Crafter score")

    def hop_frame(self, raw: np.ndarray) -> np.ndarray:
        # paper B.1: the Hopfield module reads grey-scaled observations, as Atari's frames; the semantic
        # view's codes have no colour channels (as MiniHack's glyphs)
        return grey(raw) if raw.ndim == 3 else raw

    @property
    def renderer(self) -> str:  # type: ignore[override]
        from illm_tools.envs.crafter_text import RENDERER_NAME, RENDERER_VERSION

        return f"{RENDERER_NAME}@{RENDERER_VERSION}"

    def env_ids(self) -> list[str]:
        # the pixel ids first: a listing (`illm envs`) describes a suite by its first id's view
        return sorted(ENV_IDS, key=lambda env_id: (is_semantic(env_id), env_id))

    def options(self, env_id: str) -> tuple[str, ...]:
        return SEMANTIC_OPTIONS if is_semantic(env_id) else OPTIONS

    def make(self, env_id: str, *, action_space: str, render_text: bool = True, **options: Any):
        noisy = float(options.pop("noisy_tv", 0.0))
        for key in ("area", "view", "size"):
            if isinstance(options.get(key), (int, str)):
                options[key] = tuple(int(v) for v in str(options[key]).split("x"))  # "64x64" or 64
        env = CrafterEnv(reward=ENV_IDS[env_id], render_text=render_text, semantic=is_semantic(env_id), **options)
        if noisy:  # paper Table 4's noisy TV on the picture
            from illm_tools.envs.noisy_tv import NoisyTV

            return NoisyTV(env, noisy)
        return env

    def obs_spec(self, env_id: str) -> ObsSpec:
        if is_semantic(env_id):
            size = sum(int(np.prod(shape)) for shape in SEMANTIC_PARTS.values())
            return ObsSpec(shape=(size,), dtype="uint8", kind="cells", parts=dict(SEMANTIC_PARTS),
                           description="the picture's 9x7 cells as material and object codes, the inventory's "
                                       "counts and the daylight (no picture drawn)")
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
