"""Captions of BabyAI/MiniGrid transitions: what the agent just did, in words, for ELLM's reward
(the caption's similarity to the goals the LLM suggested; `illm_tools.intrinsic.ellm`).

ELLM (Du et al. 2023) compares the suggested goals with a transition captioner's description of
(o_t, a_t, o_{t+1}). Here the captioner reads MiniGrid's egocentric (object, colour, state) views,
the ones the BabyAI-Text renderer describes (`babyai.py`: indexed [x, y], the agent at the bottom
middle facing up, the cell in front just above it, the carried object drawn in the agent's own
cell), and the action's name:

  turn left / turn right   "you turned left" / "you turned right" (always happens)
  go forward               "you went forward" when the cell in front can be entered (empty, an open
                           door, goal, lava, floor: MiniGrid's `can_overlap`); else nothing happened
  pick up                  "you picked up the red ball": the agent's cell holds an object after and
                           did not before
  drop                     "you dropped the blue key": the agent's cell held an object before and
                           does not after
  toggle                   "you opened the yellow door" / "you closed the yellow door": the door in
                           front changed state; "you opened the green box": the box in front is gone
  anything else            "you did nothing" (sleep, do nothing, think; an action that changed
                           nothing): ELLM's own caption for such steps, never rewarded

The effects of pick up, drop and toggle are read from the change between the two views. Where the
view after is not available (the last transition of an episode: the env pool resets in the same
step, so its next view is the next episode's first), they are predicted from the view before with
MiniGrid's rules (pick up: a key, ball or box in front and nothing carried; drop: something carried
and an empty cell in front; toggle: a door opens or closes, a locked one opens only for a carried
key of its colour, a box opens); tests check both ways agree wherever both apply.

CHANGING A CAPTION IN ANY WAY MUST BUMP `CAPTIONER_VERSION` (the ELLM bonus records it).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from minigrid.core.constants import IDX_TO_COLOR, IDX_TO_OBJECT, OBJECT_TO_IDX, STATE_TO_IDX

from illm_tools.envs.babyai import ACTION_SPACES

CAPTIONER_NAME = "babyai-captions"
CAPTIONER_VERSION = 1
NOTHING = "you did nothing"
"""The caption of a transition that changed nothing (ELLM's; the bonus never pays it)."""
ACTION_NAMES: tuple[str, ...] = ACTION_SPACES["irrelevant"]
"""Action index -> name for every BabyAI action space (each space is a prefix of this one)."""

_CARRIABLE = tuple(OBJECT_TO_IDX[name] for name in ("key", "ball", "box"))
_ENTERABLE = tuple(OBJECT_TO_IDX[name] for name in ("empty", "goal", "lava", "floor"))
_EMPTY, _DOOR, _BOX, _KEY = (OBJECT_TO_IDX[n] for n in ("empty", "door", "box", "key"))
_OPEN, _CLOSED, _LOCKED = (STATE_TO_IDX[n] for n in ("open", "closed", "locked"))


def captioner() -> str:
    """"<name>@<version>" of the captions (what a run records)."""
    return f"{CAPTIONER_NAME}@{CAPTIONER_VERSION}"


def _thing(cell: np.ndarray) -> str:
    return f"the {IDX_TO_COLOR[int(cell[1])]} {IDX_TO_OBJECT[int(cell[0])]}"


def caption(before: np.ndarray, action: str, after: np.ndarray | None = None) -> str:
    """The caption of one transition: the view before (uint8 [W, H, 3]), the action's name, and the
    view after (None where it is not this episode's: the effect is then predicted)."""
    ax, ay = before.shape[0] // 2, before.shape[1] - 1
    front, held = before[ax, ay - 1], before[ax, ay]
    carrying = int(held[0]) in _CARRIABLE
    if action in ("turn left", "turn right"):
        return f"you turned {action.split()[1]}"
    if action == "go forward":
        enters = int(front[0]) in _ENTERABLE or (int(front[0]) == _DOOR and int(front[2]) == _OPEN)
        return "you went forward" if enters else NOTHING
    if action == "pick up":
        if after is None:
            return f"you picked up {_thing(front)}" if int(front[0]) in _CARRIABLE and not carrying else NOTHING
        now = after[ax, ay]
        return f"you picked up {_thing(now)}" if not carrying and int(now[0]) in _CARRIABLE else NOTHING
    if action == "drop":
        if after is None:
            return f"you dropped {_thing(held)}" if carrying and int(front[0]) == _EMPTY else NOTHING
        return f"you dropped {_thing(held)}" if carrying and int(after[ax, ay, 0]) not in _CARRIABLE else NOTHING
    if action == "toggle":
        return _toggle(front, held, carrying, None if after is None else after[ax, ay - 1])
    return NOTHING


def _toggle(front: np.ndarray, held: np.ndarray, carrying: bool, front_after: np.ndarray | None) -> str:
    kind, state = int(front[0]), int(front[2])
    if kind == _BOX:
        opened = front_after is None or not np.array_equal(front_after, front)
        return f"you opened {_thing(front)}" if opened else NOTHING
    if kind != _DOOR:
        return NOTHING
    if front_after is not None:
        new = int(front_after[2]) if int(front_after[0]) == _DOOR else state
    elif state == _LOCKED:
        key = carrying and int(held[0]) == _KEY and int(held[1]) == int(front[1])
        new = _OPEN if key else _LOCKED
    else:
        new = _CLOSED if state == _OPEN else _OPEN
    if new == state:
        return NOTHING
    return f"you {'opened' if new == _OPEN else 'closed'} {_thing(front)}"


def caption_transitions(before: np.ndarray, actions: Sequence[int], after: np.ndarray,
                        ends: Sequence[bool]) -> list[str]:
    """Captions of B transitions: views uint8 [B, W, H, 3] before and after, action indices, and
    `ends` (True where the transition ended its episode, so `after` is the next episode's)."""
    return [caption(b, ACTION_NAMES[int(a)], None if e else n)
            for b, a, n, e in zip(before, actions, after, ends)]
