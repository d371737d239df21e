"""The text state of one agent step, as every language task sees it, and the two ways to build it:
from a logged trajectory table (`illm annotate`) and from live rollouts (`illm train`).

Both paths must yield identical records for the same step, or trainer keys would miss the cache.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import pyarrow as pa


@dataclass(frozen=True)
class StateRecord:
    """Everything that determines the LLM's answer for one agent step (text side).

    `history` holds the last K (observation text, action text) pairs *before* `observation`,
    oldest first; it restarts empty at every episode start.
    """

    mission: str
    history: tuple[tuple[str, str], ...]
    observation: str
    valid_actions: tuple[str, ...]


class HistoryTracker:
    """Per-env rolling window of the last K (observation text, action text) pairs.

    Call `records(...)` before stepping to get each env's current `StateRecord`, then
    `push(...)` with the actions taken and the episode ends the step reported.
    """

    def __init__(self, num_envs: int, k: int, valid_actions: Sequence[str]):
        self.k = k
        self.valid_actions = tuple(valid_actions)
        self._hist = [deque(maxlen=k) for _ in range(num_envs)]

    def records(self, missions: Sequence[str], texts: Sequence[str]) -> list[StateRecord]:
        return [StateRecord(m, tuple(h), t, self.valid_actions)
                for m, t, h in zip(missions, texts, self._hist)]

    def push(self, texts: Sequence[str], actions: Sequence[int], dones: Sequence[bool]) -> None:
        for h, text, a, done in zip(self._hist, texts, actions, dones):
            if done:
                h.clear()
            elif self.k:
                h.append((text, self.valid_actions[int(a)]))

    def reset(self) -> None:
        for h in self._hist:
            h.clear()


TABLE_COLUMNS = ["episode_id", "step", "env_id", "mission", "obs_text", "action_text", "valid_actions"]


def records_from_table(table: pa.Table, history_len: int) -> tuple[list[StateRecord], list[str]]:
    """One record per row of a trajectory table (any row order), with the history rebuilt from
    the preceding rows of the same episode. Returns the records and each row's env id, in the
    table's row order. A row whose episode misses earlier steps gets the history it has."""
    cols = {name: table.column(name).to_pylist() for name in TABLE_COLUMNS}
    order = sorted(range(table.num_rows), key=lambda i: (cols["episode_id"][i], cols["step"][i]))
    records: list[StateRecord | None] = [None] * table.num_rows
    window: deque[tuple[str, str]] = deque(maxlen=history_len)
    episode = prev_step = None
    for i in order:
        ep, step = cols["episode_id"][i], cols["step"][i]
        if ep != episode or step != (prev_step or 0) + 1:
            window.clear()
        episode, prev_step = ep, step
        text = cols["obs_text"][i] or ""
        records[i] = StateRecord(cols["mission"][i], tuple(window), text, tuple(cols["valid_actions"][i]))
        if history_len:
            window.append((text, cols["action_text"][i]))
    return records, cols["env_id"]  # type: ignore[return-value]
