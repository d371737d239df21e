"""What a set of visited states costs to annotate and how much of it a cache already answers.

Owns `VisitedStates`: the distinct states of a stream of agent steps (a trajectory dataset, or a
training run's rollouts), most visited first, with each state's step count and its cache keys per
language task. Bulk annotation takes its `--limit N` states from the front of this order (the N
states that cover the most steps), `illm data coverage` prints its curves, and the annotate stage
reports the share of steps the cache covers after a run.

A state is *covered* when the cache holds the keys of every requested task for it: that is when
the trainer has a target for the step (`illm_tools.rl.targets` needs both the action and the
summary row).

The top-k curve of a dataset is in-sample: it says what share of *these* steps the k most visited
states cover. A training run plays other episodes, and on levels with many objects its views
rarely repeat a collection's (BabyAI-GoToLocal-v0, history 0: all 18,088 distinct states of a
50,000-step random collection cover 39% of a second collection's steps). `heldout_curve` estimates
what a new run would get: the top k of half the dataset's episodes against the other half's steps.
`ahead_warning` turns that estimate into one line when annotating ahead cannot pay.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from illm_tools.llm.spec import LLMSpec
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.annotation_setup import AnnotationSetup
from illm_tools.tasks.state import StateRecord

TOP_K = (100, 1_000, 10_000)
"""The points of the "steps covered by the k most visited states" curve that are reported."""

AHEAD_FLOOR = 0.10
"""Below this held-out share (a new episode's steps found among *all* of a collection's states), annotating
the collection ahead gives a run targets on too few steps to be worth its LLM time: `ahead_warning` says so.
A judgement, not a measurement: at 2% of the steps (GoToLocal, 2,000 steps, history 0) a short run's
bonus is paid almost nowhere."""


@dataclass
class VisitedStates:
    """Distinct states, most visited first (ties: first visited first)."""

    records: list[StateRecord]
    builders: list[PromptBuilder]
    """The prompt builder of each state's env (renderer, templates, history length, model)."""
    steps: np.ndarray
    """int64 [n]: steps that visited each state."""
    tasks: tuple[str, ...]
    keys: list[tuple[str, ...]]
    """Per state, its cache key of each task in `tasks`."""

    @classmethod
    def count(cls, records: Sequence[StateRecord], env_ids: Sequence[str], renderers: Sequence[str],
              builder_for: Callable[[str, str], PromptBuilder], tasks: Sequence[str]) -> VisitedStates:
        """Count the visits of each distinct (state, env, renderer) and key the distinct ones."""
        counts = Counter(zip(records, env_ids, renderers))
        ordered = sorted(counts.items(), key=lambda item: -item[1])  # stable: ties keep first visits first
        states, builders, keys = [], [], []
        for (record, env_id, renderer), _n in ordered:
            builder = builder_for(env_id, renderer)
            keys.append(builder.state_keys(record, tasks))
            states.append(record)
            builders.append(builder)
        steps = np.fromiter((n for _, n in ordered), np.int64, len(ordered))
        return cls(states, builders, steps, tuple(tasks), keys)

    def __len__(self) -> int:
        return len(self.records)

    @property
    def total_steps(self) -> int:
        return int(self.steps.sum())

    def top(self, limit: int | None) -> VisitedStates:
        """The `limit` most visited states (all when None)."""
        if limit is None or limit >= len(self):
            return self
        return VisitedStates(self.records[:limit], self.builders[:limit], self.steps[:limit], self.tasks,
                             self.keys[:limit])

    def covered(self, cache) -> np.ndarray:
        """bool [n]: states whose every task's key the cache holds."""
        if not len(self):
            return np.zeros(0, bool)
        flat = [k for keys in self.keys for k in keys]
        return cache.contains(flat).reshape(len(self), len(self.tasks)).all(axis=1)

    def step_share(self, mask: np.ndarray | None = None) -> float:
        """Share of all counted steps that the states in `mask` (all when None) cover."""
        total = self.total_steps
        if not total:
            return 0.0
        return float(self.steps.sum() if mask is None else self.steps[mask].sum()) / total

    def top_k_curve(self, ks: Sequence[int] = TOP_K) -> dict[int, float]:
        """Share of steps covered by the k most visited states, for each k."""
        total = max(self.total_steps, 1)
        cum = np.cumsum(self.steps)
        return {k: float(cum[min(k, len(cum)) - 1]) / total if len(cum) else 0.0 for k in ks}


def heldout_curve(records: Sequence[StateRecord], env_ids: Sequence[str], renderers: Sequence[str],
                  episodes: Sequence, ks: Sequence[int] = TOP_K) -> dict[str, float]:
    """Share of the steps of every second episode (sorted by id) that the k most visited states
    of the other episodes cover, for each k, and under "all" the share any of them covers: an
    estimate of the coverage a cache annotated from this data gives a run on other episodes."""
    ids = {e: i for i, e in enumerate(sorted(set(episodes)))}
    seen: Counter = Counter()
    held: Counter = Counter()
    for state, episode in zip(zip(records, env_ids, renderers), episodes):
        (held if ids[episode] % 2 else seen)[state] += 1
    total = max(sum(held.values()), 1)
    ranked = [state for state, _ in seen.most_common()]  # ties: first counted first
    out = {}
    for k in ks:
        top = set(ranked[:k])
        out[str(k)] = sum(n for state, n in held.items() if state in top) / total
    out["all"] = sum(n for state, n in held.items() if state in seen) / total
    return out


def measure_coverage(data, *, cache=None, histories: Sequence[int] = (0, 1, 3), llm: LLMSpec | None = None,
                     layout: str = "shared", tasks: Sequence[str] = ("action", "summary")) -> list[dict]:
    """`illm data coverage`: per history length, the dataset's distinct states, the share of its
    steps the cache answers (for this model setup), the top-k curve and its held-out estimate
    (`heldout_curve`). No model is loaded: the keys need only the model's fingerprint."""
    from illm_tools.cache.store import AnnotationCache
    from illm_tools.data.trajectories import open_table, require_text
    from illm_tools.errors import UsageError
    from illm_tools.tasks.registry import parse_tasks
    from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table

    tasks = parse_tasks(tasks)
    if not histories or min(histories) < 0:
        raise UsageError("--history must be 0 or more (repeat the option for several lengths)")
    table = open_table(data, columns=TABLE_COLUMNS + ["renderer"])
    require_text(table, data)
    if cache is not None and not (Path(cache) / "manifest.json").is_file():
        raise UsageError(f"no annotation cache at {cache}: check the path, or leave --cache out to see only the costs")
    ann = AnnotationCache(cache) if cache is not None else None
    llm = (llm or LLMSpec()).placed()
    renderers = table.column("renderer").to_pylist()
    episodes = table.column("episode_id").to_pylist()
    out = []
    for k in histories:
        records, env_ids = records_from_table(table, k)
        builders: dict[tuple[str, str], PromptBuilder] = {}

        def builder_for(env_id: str, renderer: str, k: int = k) -> PromptBuilder:
            if (env_id, renderer) not in builders:
                setup = AnnotationSetup(env_id, renderer, tasks, history_len=k, layout=layout)
                builders[env_id, renderer] = setup.builder_of(llm)
            return builders[env_id, renderer]

        visited = VisitedStates.count(records, env_ids, renderers, builder_for, tasks)
        covered = visited.covered(ann) if ann is not None else np.zeros(len(visited), bool)
        out.append({
            "history": k, "steps": visited.total_steps, "distinct_states": len(visited),
            "distinct_share": len(visited) / max(visited.total_steps, 1),
            "cached_states": int(covered.sum()), "cached_step_share": visited.step_share(covered),
            "top_k_step_share": {str(k_): v for k_, v in visited.top_k_curve().items()},
            "heldout_top_k_step_share": heldout_curve(records, env_ids, renderers, episodes),
            "episodes": len(set(episodes)),
        })
    return out


def ahead_warning(rows: Sequence[dict], floor: float = AHEAD_FLOOR) -> str | None:
    """One line when `measure_coverage` finds that annotating this collection ahead will not help a
    run at some history (its held-out "all" share under `floor`), with what to do instead: the lowest
    history that does reach the floor, else a larger collection or the live fallback. None when
    every history reaches it, or when the data has too few episodes to hold half of them out."""
    if not rows or rows[0].get("episodes", 0) < 2:
        return None
    share = {r["history"]: r["heldout_top_k_step_share"]["all"] for r in rows}
    low = sorted(k for k, v in share.items() if v < floor)
    if not low:
        return None
    found = "; ".join(f"history {k}: {share[k]:.1%}" for k in low)
    line = (f"warning: annotating ahead will not help at history {', '.join(map(str, low))}: a run's new episodes "
            f"would find under {floor:.0%} of their steps among the states of these {rows[0]['steps']:,} steps ({found})")
    good = sorted(k for k, v in share.items() if v >= floor)
    if good:
        return (f"{line}; annotate and train with --history {good[0]} ({share[good[0]]:.0%} found), "
                "or let the live fallback annotate the run's own states (`illm train --live-budget N`)")
    return (f"{line}; try a lower --history, collect more steps (a larger collection repeats more of a run's "
            "states), or let the live fallback annotate the run's own states (`illm train --live-budget N`)")
