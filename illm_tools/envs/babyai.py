"""BabyAI-Text: the text renderer for MiniGrid/BabyAI observations, the action vocabularies of
paper Table 5, and the gymnasium wrapper that puts the rendered text into `info`.

The renderer follows paper Appendix C.1 and the BabyAI-Text code of GLAM
(flowersteam/Grounding_LLMs_with_online_RL, `babyai-text/gym-minigrid/gym_minigrid/minigrid.py`,
`MiniGridEnv.gen_graph`). Sentences, in this order, joined with ", " as GLAM's prompts do:

1. "You carry a <colour> <object>" when the agent's own cell (bottom middle of the view) holds an
   object: MiniGrid draws the carried object there.
2. Walls, GLAM's rule: cast a ray from the agent straight forward, then to its left, then to its
   right (along the agent's own row); skip unseen and empty cells; if the first other cell is a
   wall, say "You see a wall N steps forward|left|right". Other walls are not described.
3. Every other visible non-empty, non-wall cell, column by column from the agent's left, far to
   near within a column (GLAM's loop order): "You see a <colour> <object> <location>", doors as
   "You see a closed|locked <colour> door ..." / "You see an open <colour> door ..." (GLAM's code
   writes "a open" through a comparison bug; the paper's template says "a(n)", so we write "an").
   <location> is "N steps left|right", "N steps forward" or "N steps left|right and M steps
   forward", with "1 step" singular.

CHANGING THE RENDERED TEXT IN ANY WAY MUST BUMP `RENDERER_VERSION`: "babyai-text@<version>" goes
into every annotation cache key, so a changed renderer with an unchanged version would silently
serve annotations of other texts.
"""
from __future__ import annotations

import contextlib
import functools
import inspect
import io
import logging
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator
from minigrid.core.actions import Actions
from minigrid.core.constants import IDX_TO_COLOR, IDX_TO_OBJECT, OBJECT_TO_IDX, STATE_TO_IDX

from illm_tools.envs.suite import ObsSpec, Suite
from illm_tools.errors import UsageError

RENDERER_NAME = "babyai-text"
RENDERER_VERSION = 1

log = logging.getLogger(__name__)

_UNSEEN, _EMPTY, _WALL = OBJECT_TO_IDX["unseen"], OBJECT_TO_IDX["empty"], OBJECT_TO_IDX["wall"]
_DOOR = OBJECT_TO_IDX["door"]
_CARRIABLE = tuple(OBJECT_TO_IDX[name] for name in ("key", "ball", "box"))
_IDX_TO_STATE = {idx: name for name, idx in STATE_TO_IDX.items()}

# Action vocabularies of paper Table 5 (Appendix D.6), each name mapped to a MiniGrid action.
# The three irrelevant actions map to MiniGrid's `done`, which changes nothing in the world and
# still counts one step toward the time limit (see `_check_done_is_noop`).
_MINIGRID_ACTION = {
    "turn left": Actions.left, "turn right": Actions.right, "go forward": Actions.forward,
    "pick up": Actions.pickup, "drop": Actions.drop, "toggle": Actions.toggle,
    "sleep": Actions.done, "do nothing": Actions.done, "think": Actions.done,
}
ACTION_SPACES: dict[str, tuple[str, ...]] = {
    "original": ("turn left", "turn right", "go forward"),
    "augmented": ("turn left", "turn right", "go forward", "pick up", "drop", "toggle"),
    "irrelevant": ("turn left", "turn right", "go forward", "pick up", "drop", "toggle",
                   "sleep", "do nothing", "think"),
}
DEFAULT_ACTION_SPACE = "augmented"
# GoTo levels whose rooms are joined by closed doors: "go forward" cannot pass one, so they keep
# "toggle" (GoToImpUnlock also needs "pick up" for the key); GoToOpen and GoToObjMazeOpen open them.
_GOTO_WITH_CLOSED_DOORS = ("BabyAI-GoTo-", "BabyAI-GoToObjMaze", "BabyAI-GoToSeq", "BabyAI-GoToImpUnlock")


def default_action_space(env_id: str) -> str:
    """"original" (turn left, turn right, go forward) for the BabyAI "Go to" levels, as in paper
    Tables 1 and 5 (D.6: "the only 3 useful actions"); "augmented" for every other level and for
    GoTo levels behind closed doors."""
    if not env_id.startswith("BabyAI-GoTo"):
        return DEFAULT_ACTION_SPACE
    if env_id.startswith(_GOTO_WITH_CLOSED_DOORS) and not env_id.startswith("BabyAI-GoToObjMazeOpen"):
        return DEFAULT_ACTION_SPACE
    return "original"


def _steps(n: int, direction: str) -> str:
    return f"{n} step {direction}" if n == 1 else f"{n} steps {direction}"


def _location(dx: int, forward: int) -> str:
    """Where a cell lies: dx columns right (negative: left) and `forward` rows ahead."""
    side = _steps(dx, "right") if dx > 0 else _steps(-dx, "left")
    if dx == 0:
        return _steps(forward, "forward")
    if forward == 0:
        return side
    return f"{side} and {_steps(forward, 'forward')}"


def _object_phrase(obj: int, colour: int, state: int) -> str:
    name = f"{IDX_TO_COLOR[colour]} {IDX_TO_OBJECT[obj]}"
    if obj != _DOOR:
        return f"a {name}"
    door_state = _IDX_TO_STATE[state]
    return f"{'an' if door_state == 'open' else 'a'} {door_state} {name}"


def describe(image: np.ndarray) -> list[str]:
    """The BabyAI-Text sentences for one egocentric view (MiniGrid's `image`, indexed [x, y, channel]
    with channels (object, colour, state); the agent sits at the bottom middle facing up)."""
    view = np.ascontiguousarray(image, dtype=np.uint8)
    return _describe(view.tobytes(), view.shape[0], view.shape[1])


_OBJECT_CELLS = bytes(1 if code > _WALL else 0 for code in range(256))  # translate(): 1 where an object lies
_SENTENCE_LIMIT = 100_000


def _describe(data: bytes, width: int, height: int) -> list[str]:
    """`describe` over the view's bytes (C order [x, y, channel]). Plain Python over the 49 cells:
    a view is too small for numpy, whose per-call costs made rendering 2.5x slower (it is ~3% of
    an iLLM update on BabyAI: every new view of every step is rendered). The objects' cells are
    found by `bytes.find` over a translated copy, and each (cell, object) sentence is made once
    (3.9 -> 2.7 us a view over 8,267 distinct views of four levels' random rollouts)."""
    ax, ay = width // 2, height - 1
    types = data[::3]  # cell (x, y)'s object at x * height + y
    sentences = []
    here = ax * height + ay
    if types[here] in _CARRIABLE:
        sentences.append(f"You carry a {IDX_TO_COLOR[data[3 * here + 1]]} {IDX_TO_OBJECT[types[here]]}")
    # MiniGrid views are odd-sized and at least 3x3, so ax and ay are >= 1 and the rays are well formed:
    # forward (up the agent's column), left and right (along its row), each to the first non-empty cell
    for cells, direction in ((range(here - 1, here - ay - 1, -1), "forward"),
                             (range(here - height, -1, -height), "left"),
                             (range(here + height, width * height, height), "right")):
        for distance, cell in enumerate(cells, 1):
            if types[cell] > _EMPTY:  # skip unseen (0) and empty (1) cells
                if types[cell] == _WALL:
                    sentences.append(f"You see a wall {_steps(distance, direction)}")
                break
    objects = types.translate(_OBJECT_CELLS)
    cell = objects.find(1)
    while cell >= 0:  # row-major over [x, y]: GLAM's column-by-column order
        if cell != here:
            sentences.append(_object_sentence(cell, width, height, data[3 * cell:3 * cell + 3]))
        cell = objects.find(1, cell + 1)
    return sentences


_sentences: dict[tuple, str] = {}


def _object_sentence(cell: int, width: int, height: int, codes: bytes) -> str:
    """"You see <object> <where>" for the object `codes` (object, colour, state) at `cell` of a view."""
    key = (cell, width, height, codes)
    sentence = _sentences.get(key)
    if sentence is None:
        if len(_sentences) > _SENTENCE_LIMIT:
            _sentences.clear()
        x, y = divmod(cell, height)
        sentence = _sentences[key] = f"You see {_object_phrase(*codes)} {_location(x - width // 2, height - 1 - y)}"
    return sentence


def render_text(image: np.ndarray) -> str:
    """The BabyAI-Text description of one view: `describe`'s sentences joined with ", ". Rendered
    once per distinct view (memoised by its bytes: a run sees the same views again and again)."""
    view = image if image.dtype == np.uint8 else image.astype(np.uint8)  # tobytes writes C order
    return _render(view.tobytes(), view.shape)


@functools.lru_cache(maxsize=65536)
def _render(data: bytes, shape: tuple[int, ...]) -> str:
    return ", ".join(_describe(data, shape[0], shape[1]))


def forget_rendered() -> None:
    """Empty the memo of rendered views (it lives as long as the process): runs timed one after
    another in one process each start as a fresh process would (`benchmarks/train.py`)."""
    _render.cache_clear()
    _sentences.clear()


def _check_done_is_noop(action_space: str) -> None:
    # With BABYAI_DONE_ACTIONS set, BabyAI's verifier ends the episode on `done`; the irrelevant
    # actions would then no longer be irrelevant. minigrid reads the flag once, at import.
    from minigrid.envs.babyai.core import verifier

    if action_space == "irrelevant" and verifier.use_done_actions:
        raise UsageError("the 'irrelevant' action space maps sleep/do nothing/think to MiniGrid's "
                         "done action, which BABYAI_DONE_ACTIONS makes end the episode: unset it")


class BabyAITextEnv(gym.Wrapper):
    """A MiniGrid/BabyAI env with a text action vocabulary; `info` carries `text` (the rendered
    observation, "" when render_text=False), `mission` and `valid_actions` after reset and step.
    Observations are MiniGrid's own dict (image, direction, mission)."""

    def __init__(self, env: gym.Env, action_space: str = DEFAULT_ACTION_SPACE, render_text: bool = True):
        if action_space not in ACTION_SPACES:
            raise UsageError(f"unknown action space {action_space!r}; choose one of {', '.join(ACTION_SPACES)}")
        _check_done_is_noop(action_space)
        super().__init__(env)
        self.action_names: tuple[str, ...] = ACTION_SPACES[action_space]
        self.action_space = gym.spaces.Discrete(len(self.action_names))
        self.render_text = render_text
        self._to_minigrid = [int(_MINIGRID_ACTION[name]) for name in self.action_names]

    def _info(self, obs: dict, info: dict) -> dict:
        info["text"] = render_text(obs["image"]) if self.render_text else ""
        info["mission"] = obs["mission"]
        info["valid_actions"] = list(self.action_names)
        grid = self.env.unwrapped
        info["agent_pos"] = np.array(grid.agent_pos, dtype=np.int64)  # (x, y): visitation counts
        info["grid_size"] = np.array((grid.width, grid.height), dtype=np.int64)
        return info

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        # BabyAI's level generator print()s every rejected sample; keep that out of our output.
        with contextlib.redirect_stdout(io.StringIO()) as chatter:
            obs, info = self.env.reset(seed=seed, options=options)
        if chatter.getvalue():
            log.debug("level generation: %s", chatter.getvalue().strip())
        return obs, self._info(obs, info)

    def step(self, action: Any):
        try:
            minigrid_action = self._to_minigrid[int(action)]
        except (IndexError, TypeError, ValueError):
            raise UsageError(f"action {action!r} is not in 0..{len(self.action_names) - 1} "
                             f"({', '.join(self.action_names)})") from None
        obs, reward, terminated, truncated, info = self.env.step(minigrid_action)
        if terminated or truncated:  # BabyAI pays a reward only when the mission is done
            info["success"] = bool(terminated and reward > 0)
        return obs, reward, terminated, truncated, self._info(obs, info)


def make_babyai_text(env_id: str, *, action_space: str = DEFAULT_ACTION_SPACE, num_dists: int | None = None,
                     render_text: bool = True, **kwargs: Any) -> BabyAITextEnv:
    """gym.make(env_id) wrapped as BabyAITextEnv; `num_dists` only for levels whose class takes it."""
    if num_dists is not None:
        if not accepts_num_dists(env_id):
            raise UsageError(f"{env_id} has no distractor setting (num_dists); drop --num-dists or use a "
                             "level that has one, e.g. BabyAI-GoToLocal-v0")
        if int(num_dists) < 0:
            raise UsageError(f"num_dists must be >= 0, got {num_dists}")
        kwargs["num_dists"] = int(num_dists)
    return BabyAITextEnv(gym.make(env_id, **kwargs), action_space=action_space, render_text=render_text)


def accepts_num_dists(env_id: str) -> bool:
    """Whether the level's class takes a `num_dists` argument (GoTo*, Synth*, ...; paper Table 1)."""
    creator = load_env_creator(gym.spec(env_id).entry_point)
    return "num_dists" in inspect.signature(creator).parameters


@functools.lru_cache(maxsize=1)
def env_ids() -> list[str]:
    """The BabyAI-* and MiniGrid-* ids that minigrid registers (importing minigrid registers them)."""
    import minigrid  # noqa: F401  (registers the ids)

    return sorted(k for k in gym.registry if k.startswith(("BabyAI-", "MiniGrid-")))



class BabyAISuite(Suite):
    """BabyAI and MiniGrid: the symbolic egocentric view and the mission, rendered as BabyAI-Text."""

    name = "babyai"
    prefixes = ("BabyAI-", "MiniGrid-")
    renderer = f"{RENDERER_NAME}@{RENDERER_VERSION}"
    description = "BabyAI and MiniGrid levels (minigrid), text as in BabyAI-Text (paper C.1)"

    def env_ids(self) -> list[str]:
        return env_ids()

    def make(self, env_id: str, *, action_space: str, render_text: bool = True, **options: Any) -> BabyAITextEnv:
        return make_babyai_text(env_id, action_space=action_space, render_text=render_text, **options)

    def options(self, env_id: str) -> tuple[str, ...]:
        from illm_tools.envs.suite import gym_options

        return (*gym_options(env_id), "num_dists")  # num_dists: the maker says which levels take it

    def action_spaces(self, env_id: str) -> tuple[str, ...]:
        first = default_action_space(env_id)
        return (first, *(name for name in ACTION_SPACES if name != first))

    def obs_spec(self, env_id: str) -> ObsSpec:
        return ObsSpec(shape=(7, 7, 3), dtype="uint8", kind="grid",
                       description="the 7x7 egocentric view as (object, colour, state) codes, and the mission")

    def policy_obs(self, obs: dict) -> np.ndarray:
        return obs["image"]


SUITE = BabyAISuite()
