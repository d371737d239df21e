"""Hop states: the translated window of recent steps, its records (cache keys) and Z_h.

A hop state is the window of the last K = history_len + 1 steps of one episode (fewer near its
start), each step being (raw observation, previous action). `HopRecord` is a `StateRecord` whose texts name those steps by
content ("<sha256 of the raw observation's dtype, shape and bytes> after <previous action>"), so
the cache's keys (built from the rendered prompt and the setup, `illm_tools.tasks.prompts`) change
with the observations and actions and with nothing else; the setup's renderer field,
`hop_renderer`, carries the projection's seed, beta and the window, and the model fingerprint is
in every key already. The arrays ride along (not compared, not hashed) for the LLM calls.

`HopTracker` builds these records step by step during a rollout, as `HistoryTracker` builds text
records, and keeps each step's translation; `HopContext` turns the windows into Z_h, the LLM's
last hidden state after reading the translated steps as input embeddings (no prompt around them),
which the policy reads beside its own torso. Both run every rollout step: on a CPU this costs one
forward pass of the LLM over N windows of at most K positions per step (docs/measured.md: the cost of hop).
"""
from __future__ import annotations

import hashlib
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from illm_tools.hop.translate import FrozenHopfield
from illm_tools.tasks.state import StateRecord

START = "start"
"""The previous action of an episode's first step."""


def digest(raw: np.ndarray) -> str:
    """Content name of one raw observation (dtype, shape and bytes)."""
    h = hashlib.sha256(f"{raw.dtype.str}{raw.shape}".encode())
    h.update(np.ascontiguousarray(raw).tobytes())
    return h.hexdigest()[:24]


def step_name(raw: np.ndarray, prev_action: str | None) -> str:
    return f"{digest(raw)} after {prev_action or START}"


@dataclass(frozen=True)
class HopRecord(StateRecord):
    """A `StateRecord` of a hop state; `frames` and `prev_actions` (oldest first, the current step
    last; -1: none) are what the LLM reads, not part of equality or hashing."""

    frames: tuple = field(default=(), compare=False, hash=False, repr=False)
    prev_actions: tuple = field(default=(), compare=False, hash=False, repr=False)


RAW_COLUMNS = ["episode_id", "step", "env_id", "mission", "obs_raw", "obs_shape", "obs_dtype", "action",
               "valid_actions"]
"""The trajectory columns hop records are built from."""


def hop_records_from_table(table, history_len: int) -> tuple[list[HopRecord], list[str]]:
    """One hop record per row of a trajectory table (any row order; the window rebuilt from the
    preceding rows of the same episode, as `HopTracker` builds it in training), and each row's env
    id, in the table's row order. Rows without raw observations (collected with --no-raw) are
    refused in one line."""
    from illm_tools.envs import suite_of
    from illm_tools.errors import UsageError

    cols = {name: table.column(name).to_pylist() for name in RAW_COLUMNS}
    if any(raw is None for raw in cols["obs_raw"]):
        raise UsageError("the dataset has rows without raw observations (collected with --no-raw): --mode hop "
                         "translates the observations themselves; collect again without --no-raw")
    order = sorted(range(table.num_rows), key=lambda i: (cols["episode_id"][i], cols["step"][i]))
    records: list[HopRecord | None] = [None] * table.num_rows
    trackers: dict[tuple[str, ...], HopTracker] = {}
    episode = prev_step = None
    for i in order:
        actions = tuple(cols["valid_actions"][i])
        tracker = trackers.setdefault(actions, HopTracker(1, history_len, actions))
        ep, step = cols["episode_id"][i], cols["step"][i]
        if ep != episode or step != (prev_step or 0) + 1:
            tracker.reset()
        episode, prev_step = ep, step
        raw = np.frombuffer(cols["obs_raw"][i], dtype=np.dtype(cols["obs_dtype"][i])).reshape(cols["obs_shape"][i])
        (records[i],) = tracker.records([cols["mission"][i]], [suite_of(cols["env_id"][i]).hop_frame(raw)])
        tracker.push([int(cols["action"][i])], [False])
    return records, cols["env_id"]  # type: ignore[return-value]


class HopTracker:
    """Per-env window of the last `history_len` steps (raw observation, previous action, action
    taken, translation, content name) before the current one. `records()` before stepping (it also holds each
    env's current step), `HopContext.step()` to translate it, `push()` after stepping."""

    def __init__(self, num_envs: int, history_len: int, valid_actions: Sequence[str]):
        if history_len < 0:
            raise ValueError(f"--history must be 0 or more, got {history_len}")
        self.valid_actions = tuple(valid_actions)
        self._steps: list[deque] = [deque(maxlen=history_len) for _ in range(num_envs)]
        self._prev = [-1] * num_envs  # previous action of each env's current step
        self._pending: list[np.ndarray | None] = [None] * num_envs
        self._pending_name: list[str] = [""] * num_envs  # each step is hashed once, when it is current
        self._pending_x: dict[int, torch.Tensor] = {}

    def _name(self, raw: np.ndarray, prev: int) -> str:
        return step_name(raw, self.valid_actions[prev] if prev >= 0 else None)

    def records(self, missions: Sequence[str], raws: Sequence[np.ndarray]) -> list[HopRecord]:
        out = []
        for i, (mission, raw) in enumerate(zip(missions, raws)):
            raw = np.array(raw, copy=True)
            self._pending[i] = raw
            self._pending_name[i] = self._name(raw, self._prev[i])
            past = list(self._steps[i])
            history = tuple((name, self.valid_actions[a]) for _r, _p, a, _x, name in past)
            out.append(HopRecord(mission, history, self._pending_name[i], self.valid_actions,
                                 frames=tuple(r for r, *_ in past) + (raw,),
                                 prev_actions=tuple(p for _r, p, *_ in past) + (self._prev[i],)))
        return out

    def windows(self) -> list[list[tuple[np.ndarray, int, torch.Tensor | None]]]:
        """Each env's window, oldest first, ending with its current step: (raw, previous action,
        translation, None where not yet computed)."""
        return [[(r, p, x) for r, p, _a, x, _name in steps] + [(self._pending[i], self._prev[i], self._pending_x.get(i))]
                for i, steps in enumerate(self._steps)]

    def set_translation(self, i: int, x: torch.Tensor) -> None:
        """Remember env i's current step's translation (kept with the step once pushed)."""
        self._pending_x[i] = x

    def push(self, actions: Sequence[int], ends: Sequence[bool]) -> None:
        for i, (action, end) in enumerate(zip(actions, ends)):
            if end:
                self._steps[i].clear()
                self._prev[i] = -1
            else:
                self._steps[i].append((self._pending[i], self._prev[i], int(action), self._pending_x.get(i),
                                       self._pending_name[i]))
                self._prev[i] = int(action)
        self._pending_x = {}

    def reset(self) -> None:
        for i, steps in enumerate(self._steps):
            steps.clear()
            self._prev[i] = -1
        self._pending_x = {}


class HopContext:
    """Translation and Z_h for a run: the frozen Hopfield layer over the LLM backend's input
    embeddings, and the backend itself (frozen, inference only; `illm_tools.llm.backend`)."""

    def __init__(self, lm, obs_dim: int, num_actions: int, *, seed: int, beta: float):
        from illm_tools.llm.backend import as_backend

        self.lm = as_backend(lm)
        self.translator = FrozenHopfield(self.lm.input_embeddings(), obs_dim, num_actions, seed=seed, beta=beta)
        self.hidden_size = int(self.lm.hidden_size)

    def translate(self, raws: Sequence[np.ndarray], prev_actions: Sequence[int]) -> torch.Tensor:
        """[B, d] translations of (raw observation, previous action) pairs."""
        obs = torch.as_tensor(np.stack([np.asarray(r) for r in raws]))
        return self.translator(obs, torch.as_tensor(list(prev_actions), dtype=torch.long))

    def window_embeddings(self, frames: Sequence[np.ndarray], prev_actions: Sequence[int]) -> torch.Tensor:
        """[L, d] translated steps of one window, oldest first (what the language tasks read)."""
        return self.translate(frames, prev_actions)

    def z_h(self, windows: Sequence[torch.Tensor]) -> torch.Tensor:
        """float32 [B, H]: the LLM's last hidden state after reading each window [L_i, d] as input
        embeddings (no prompt around them)."""
        return self.lm.last_hidden(windows)

    def step(self, tracker: HopTracker) -> torch.Tensor:
        """Z_h of every env's current window (after `tracker.records`), translating only the new
        step of each and remembering it for the next steps."""
        windows = tracker.windows()
        new = self.translate([w[-1][0] for w in windows], [w[-1][1] for w in windows])
        stacked = []
        for i, win in enumerate(windows):
            tracker.set_translation(i, new[i])
            stacked.append(torch.stack([x if x is not None else self.translate([r], [p])[0] for r, p, x in win[:-1]]
                                       + [new[i]]))
        return self.z_h(stacked)


class HopStates:
    """iLLM(hop)'s state source (`illm_tools.rl.states.StateSource`, picked by `make_states`): the
    window of each env's recent (observation, action) steps, its hop records and Z_h, the LLM's last
    hidden state over the translated window, which the network reads beside its torso. Z_h of the
    current observations is computed once per step. `cfg` is the run's `TrainConfig`."""

    def __init__(self, cfg, suite, image_shape: tuple[int, ...], action_names: Sequence[str],
                 device: torch.device | str = "cpu", num_envs: int | None = None):
        lm = cfg.llm.load()
        self.suite, self.device = suite, device
        raw = np.asarray(suite.hop_input(np.zeros(image_shape, dtype=np.uint8)))
        self.tracker = HopTracker(num_envs or cfg.num_envs, cfg.setup.history_len, list(action_names))
        self.hop = HopContext(lm, raw.size, len(action_names), seed=cfg.setup.hop_seed, beta=cfg.setup.hop_beta)
        self.context_dim = self.hop.hidden_size
        self._now: tuple[list, torch.Tensor] | None = None

    def current(self, obs) -> tuple[list[StateRecord], torch.Tensor]:
        if self._now is None:
            records = self.tracker.records(obs.missions, [self.suite.hop_input(img) for img in obs.images])
            self._now = records, self.hop.step(self.tracker).to(self.device)
        return self._now

    def advance(self, obs, actions, ends, next_obs) -> None:
        self.tracker.push(list(actions), list(ends))
        self._now = None
        self.current(next_obs)  # the windows changed: their Z_h now, while the step's arrays are at hand
