"""LLM targets for training, read from the annotation cache, with a live fallback.

After each rollout the trainer hands every step's `StateRecord`. The keys are built by the same
`PromptBuilder` (renderer, templates, history length, model fingerprint) as `illm annotate`, so a
state annotated in bulk is a cache hit here. The distinct states the cache lacks, most visited
over the run so far first, go to the live annotator (`illm_tools.rl.live`): `sync` annotates the
first `live_budget` of them now and this rollout uses them; `async` hands them to a worker
process and a later rollout finds its answers in the shared cache. States still missing get no
target (and so no bonus) and are counted. (A cache that holds annotations but none for this run's
setup is refused before, by `illm_tools.tasks.annotation_setup.check_setup`.)

`CachedTargets` serves iLLM (the rows of the run's language tasks: action and summary by default,
any of `illm_tools.tasks.registry`'s); `GoalTargets` serves ELLM (the
`goal` rows: each state's suggested goals), with the same keys, look-up and live fallback.
`CachedTargets(shuffle_seed=...)` serves the `illm-shuffled` control: each state gets the targets
of another cached state, chosen by a fixed permutation (`ShuffledKeys`).
"""

from __future__ import annotations

import bisect
import hashlib
from collections import Counter
from collections.abc import Mapping, Sequence

import numpy as np

from illm_tools.cache.store import AnnotationCache
from illm_tools.cache.tail import ShardTail
from illm_tools.intrinsic.base import Targets
from illm_tools.tasks.calibration import ACTION_TARGETS, action_target
from illm_tools.tasks.prompts import Prompt, PromptBuilder
from illm_tools.tasks.registry import DEFAULT_TASKS, get_task, parse_tasks, text_tasks
from illm_tools.tasks.state import StateRecord

ACTION_COLUMNS = ["cand_logprob_sum", "cand_token_count", "neutral_logprob_sum"]
_MEMO_LIMIT = 500_000


class RecentMemo:
    """`values(records, compute)`: `compute(record)` of each record, once per distinct record of this
    call, reusing the last call's. Only the last call's are kept: a run-long memo reused few more
    (BabyAI, 81,920 frames: 35,168 keys computed against 36,714 at history 0, 73,610 against 73,749
    at history 3) and grew by a rollout's states every update, whose objects the garbage
    collector's full passes then read again and again."""

    def __init__(self) -> None:
        self._last: dict = {}

    def values(self, records: Sequence[StateRecord], compute) -> list:
        last, current, out = self._last, {}, []
        for r in records:
            value = current.get(r)
            if value is None:
                value = last.get(r)
                current[r] = value = compute(r) if value is None else value
            out.append(value)
        self._last = current
        return out


class CachedTargets:
    """`TargetProvider` over an `AnnotationCache` for the language tasks `tasks` (iLLM's: action and
    summary by default; any combination of the registered tasks, `illm_tools.tasks.registry`); `live`
    (`illm_tools.rl.live.SyncLive` or `AsyncLive`, writing to the same cache) enables the live
    fallback. A state has a target when the cache answers every task. The action task gives the
    action distribution: the softmax of the calibrated scores (`distribution`) or the one-hot of
    their argmax (`argmax`, the paper's choice); each text task its embedding, side by side in task
    order ([B, K * embedding_dim]). `shuffle_seed` (None: off) hands each state the targets of
    another cached state of the same task and setup, its partner under the fixed permutation
    `ShuffledKeys` with that seed; the mask stays the state's own (True where its own entries exist,
    as without the shuffle, and its partner's too), so coverage and the live fallback are unchanged."""

    def __init__(self, cache: AnnotationCache, builder: PromptBuilder, *, calibration: str,
                 num_actions: int, embedding_dim: int, action_target: str = "distribution", live=None,
                 shuffle_seed: int | None = None, tasks: Sequence[str] = DEFAULT_TASKS):
        self.cache = cache
        self.builder = builder
        self.calibration = calibration
        if action_target not in ACTION_TARGETS:
            raise ValueError(f"unknown action target {action_target!r}: use one of {', '.join(ACTION_TARGETS)}")
        self.action_target = action_target
        self.num_actions = num_actions
        self.embedding_dim = embedding_dim
        self.tasks = parse_tasks(tasks)
        self.text = text_tasks(self.tasks)
        self.live = live
        self.shuffle = ShuffledKeys(cache, builder, shuffle_seed, self.tasks) if shuffle_seed is not None else None
        self._keys = RecentMemo()  # each state's keys, per task
        self._visits: Counter[StateRecord] = Counter()
        self._last: dict[str, float] = {"cache_hit_rate": 0.0, "target_coverage": 0.0, "live_annotations": 0.0}
        self.landed_at_close = 0
        """States the live annotator put in the cache after the last rollout counted them (set by close)."""

    def keys(self, records: Sequence[StateRecord]) -> dict[str, list[str]]:
        """Each task's keys of the records, computed once per distinct record of this call or the
        last (`RecentMemo`)."""
        rows = self._keys.values(records, lambda r: self.builder.state_keys(r, self.tasks))
        return {task: [keys[i] for keys in rows] for i, task in enumerate(self.tasks)}

    def _lookup(self, keys: dict[str, list[str]]) -> tuple[dict[str, dict], np.ndarray]:
        """One cache look-up per task: (each task's columns, mask with all of them). With the
        shuffle, the columns are the partners' and the mask also asks for the state's own."""
        own = None
        if self.shuffle is not None:
            own = np.logical_and.reduce([self.cache.contains(k) for k in keys.values()])
            keys = {task: self.shuffle.partners(task, k) for task, k in keys.items()}
        columns = {task: self.cache.get_matrices(k, ACTION_COLUMNS if get_task(task).kind == "ranking" else ["embedding"],
                                                 task=task) for task, k in keys.items()}
        found = np.logical_and.reduce([c["found"] for c in columns.values()])
        return columns, found if own is None else found & own

    def _annotate_missing(self, records: Sequence[StateRecord], found: np.ndarray) -> int:
        """Live fallback: the distinct missing states, most visited over the run so far first,
        go to the live annotator (`illm_tools.rl.live`); returns the states it annotated."""
        missing = list(dict.fromkeys(r for r, f in zip(records, found) if not f))
        missing.sort(key=self._visits.__getitem__, reverse=True)  # stable: ties in rollout order
        return self.live.submit(missing, [self._visits[r] for r in missing])

    def _count_visits(self, records: Sequence[StateRecord]) -> None:
        if len(self._visits) > _MEMO_LIMIT:  # keep the states seen more than once
            self._visits = Counter({r: n for r, n in self._visits.items() if n > 1})
        self._visits.update(records)

    def _with_live(self, records: Sequence[StateRecord], lookup) -> tuple:
        """`lookup()` -> (columns, found mask) from the cache, refreshed first, with the live
        fallback run on the states it misses; returns (columns, found, cache hits, states annotated
        live). Shared by every task's provider."""
        self.cache.refresh()  # other runs may have written to the shared cache meanwhile
        columns, found = lookup()
        hits, live = int(found.sum()), 0
        if self.live is not None:
            self._count_visits(records)  # only the live fallback's priorities need them
            if not found.all():
                live = self._annotate_missing(records, found)
                if self.live.waits:  # sync: this rollout uses the new answers; async: a later one
                    columns, found = lookup()
            live += self.live.landed()
        return columns, found, hits, live

    def _record(self, steps: int, covered: int, hits: int, live: int) -> None:
        n = max(steps, 1)
        self._last = {"cache_hit_rate": hits / n, "target_coverage": covered / n, "live_annotations": float(live),
                      **(self.live.stats() if self.live is not None else {})}

    def targets(self, records: Sequence[StateRecord]) -> Targets:
        keys = self.keys(records)

        def lookup():
            return self._lookup(keys)

        columns, found, hits, live = self._with_live(records, lookup)
        b, d = len(records), self.embedding_dim
        probs = np.zeros((b, self.num_actions), np.float32)
        emb = np.zeros((b, d * len(self.text)), np.float32)
        idx = np.flatnonzero(found)
        if idx.size:
            rows = slice(None) if idx.size == b else idx  # every state found (a cached run): copies, no gathers
            if "action" in columns:
                a = columns["action"]
                scores = [a[c][rows].astype(np.float64) if a[c].shape[1] else np.full((idx.size, self.num_actions), np.nan)
                          for c in ACTION_COLUMNS]  # a column null in every row (no neutral scores): NaN, as absent
                probs[rows] = action_target(*scores, self.calibration, self.action_target)
            for j, task in enumerate(self.text):
                emb[rows, j * d:(j + 1) * d] = columns[task]["embedding"][rows]
        self._record(b, idx.size, hits, live)
        return Targets(probs, emb, found)

    def stats(self) -> Mapping[str, float]:
        """Of the last `targets` call (one rollout): share of steps found in the cache before the
        live fallback, share with a target after it, states annotated live since the last call,
        and the live annotator's queue (`live_queue`: states waiting in the async worker)."""
        return dict(self._last)

    @classmethod
    def for_run(cls, cfg, cache: AnnotationCache, builder: PromptBuilder, *, num_actions: int, live=None,
                shuffle_seed: int | None = None) -> CachedTargets:
        """The provider of a training run (its `TrainConfig`): the run's target tasks, calibration,
        action target and embedding width (the model's hidden size, set by the run's assembly)."""
        return cls(cache, builder, calibration=cfg.targets.action_score, num_actions=num_actions,
                   embedding_dim=cfg.embedding_dim, action_target=cfg.bonus.action_target, tasks=cfg.target_tasks,
                   live=live, shuffle_seed=shuffle_seed)

    def close(self) -> None:
        """Stop the live annotator (the async worker process), if any; `landed_at_close` counts the
        states it put in the cache after the last rollout's count, its shutdown's chunk included."""
        if self.live is None:
            return
        before = self.live.landed()
        self.live.close()  # the async worker's last chunk is written (and counted) while this waits for it
        self.landed_at_close = before + self.live.landed()


class GoalTargets(CachedTargets):
    """`TargetProvider` of the `goal` task (ELLM, `illm_tools.intrinsic.ellm`) over an
    `AnnotationCache`, with the same live fallback as `CachedTargets` (`live` annotating `goal`).

    `targets` answers only the mask (the state has a goal row; its action distribution and
    embedding are empty: [B, A] zeros and [B, 0]); the goals themselves, parsed at annotation time
    (`illm_tools.tasks.goals.parse_goals`, the row's `candidates`), are in `goals` after each
    call, aligned with the records (t-major), None where the state has no row yet."""

    def __init__(self, cache: AnnotationCache, builder: PromptBuilder, *, num_actions: int, live=None):
        super().__init__(cache, builder, calibration="sum", num_actions=num_actions, embedding_dim=0, live=live,
                         tasks=("goal",))
        self._goal_keys = RecentMemo()
        self.goals: list[tuple[str, ...] | None] = []
        """Per record of the last `targets` call: the state's goals (possibly none), or None."""

    @classmethod
    def for_run(cls, cfg, cache: AnnotationCache, builder: PromptBuilder, *, num_actions: int, live=None,
                shuffle_seed: int | None = None) -> GoalTargets:
        if shuffle_seed is not None:
            from illm_tools.errors import UsageError

            raise UsageError("the goal targets have no shuffled control: a method with target_shuffle reads "
                             "the heads' tasks")
        return cls(cache, builder, num_actions=num_actions, live=live)

    def goal_keys(self, records: Sequence[StateRecord]) -> list[str]:
        """The `goal` keys of the records, computed once per distinct record of this call or the last."""
        return self._goal_keys.values(records, lambda r: self.builder.task_key("goal", r))

    def targets(self, records: Sequence[StateRecord]) -> Targets:
        keys = self.goal_keys(records)

        def lookup():
            rows = self.cache.get_columns(keys, ["candidates"], task="goal")
            return rows, np.asarray(rows["found"], bool)

        rows, found, hits, live = self._with_live(records, lookup)
        self.goals = [tuple(g or ()) if f else None for g, f in zip(rows["candidates"], found)]
        b = len(records)
        self._record(b, int(found.sum()), hits, live)
        return Targets(np.zeros((b, self.num_actions), np.float32), np.zeros((b, 0), np.float32), found)


class ShuffledKeys:
    """The `illm-shuffled` control's fixed permutation of the cached states of one run's setup:
    `partners` maps each looked-up key to the key of another cached entry of the same task and
    setup, whose targets carry nothing of what the LLM said about the looked-up state.

    The pool of a task (each of the run's `tasks`) is the cache's entries this run's
    `PromptBuilder` keys as they are keyed (the key recomputed from the row's prompt and candidates
    equals the row's key: same task, template and version, layout, renderer, model fingerprint and
    decoding); a ranking task's entries (action) are grouped by their candidate list, so a
    partner's distribution covers the same valid actions; a text task's form one group.
    Every entry is ranked by a keyed hash (blake2b, 64 bits, keyed with the seed) of its state's
    rendered inputs (mission, history, observation), ties broken by key; a key's partner is the
    entry after it in rank order within its group, the last one's the first. So:
    - the permutation is one cycle through each group: no state is its own partner once its group
      holds two entries (a lone entry has no partner, and its state no target);
    - it depends only on the cache's content (the ranks come from the rows, not from shard order,
      from when a shard was read or from the look-ups), so it is the same across calls, runs and
      copies of the cache;
    - as the cache grows it stays fixed but for the new entries: each new entry takes its place
      after its predecessor in rank order, changing the partner of that one state and no other;
    - the entries of one state's tasks share their rank, so when the pools hold the same states (as
      `illm annotate` and the live fallback write them) a state takes every target from the same
      other state.
    The pool is read from the cache's shards as the manifest lists them, each shard once
    (`illm_tools.cache.tail.ShardTail`)."""

    COLUMNS = ["key", "task", "prompt", "candidates", "goal", "history", "observation"]

    def __init__(self, cache: AnnotationCache, builder: PromptBuilder, seed: int, tasks: Sequence[str] = DEFAULT_TASKS):
        self.cache, self.builder, self.seed = cache, builder, int(seed)
        self.tasks = tuple(tasks)
        self._salt = hashlib.sha256(f"illm-shuffled:{self.seed}".encode()).digest()[:16]
        self._tail = ShardTail(cache.root, self.COLUMNS)  # each listed shard's rows, once
        self._reset()

    def _reset(self) -> None:
        self._where: dict[str, dict[str, tuple]] = {t: {} for t in self.tasks}  # key -> (group, rank)
        self._groups: dict[tuple, list[tuple[int, str]]] = {}  # (task, group) -> sorted (rank, key)
        self._unsorted: set[tuple] = set()

    def rank(self, goal: str, history: str, observation: str) -> int:
        """The keyed 64-bit hash of a state's rendered inputs."""
        text = "\x1f".join((goal or "", history or "", observation or "")).encode()
        return int.from_bytes(hashlib.blake2b(text, digest_size=8, key=self._salt).digest(), "big")

    def sync(self) -> int:
        """Add the entries of the shards the manifest gained since the last call; returns how many
        (a rewritten manifest, e.g. a copy merged in place, is read again from the start)."""
        restarted, shards = self._tail.read()
        if restarted:
            self._reset()
        return sum(self._add(rows) for rows in shards)

    def _add(self, rows: list[dict]) -> int:
        added = 0
        for row in rows:
            task, key = row["task"], row["key"]
            if task not in self._where or key in self._where[task]:
                continue
            ranking = get_task(task).kind == "ranking"
            # PromptBuilder.render's candidates: " " + each valid action (rows keep them stripped)
            cands = tuple(" " + c for c in row["candidates"] or ()) if ranking else None
            prompt = Prompt(task, row["prompt"], row["goal"], row["history"], row["observation"], cands)
            if self.builder.key(prompt) != key:  # another setup's entry (or another layout's)
                continue
            group = (task, tuple(row["candidates"] or ()) if ranking else ())
            rank = self.rank(row["goal"], row["history"], row["observation"])
            self._where[task][key] = (group, rank)
            self._groups.setdefault(group, []).append((rank, key))
            self._unsorted.add(group)
            added += 1
        return added

    def partners(self, task: str, keys: Sequence[str]) -> list[str]:
        """Each key's partner ("" where the key is not in the pool or its group has one entry)."""
        self.sync()
        for group in self._unsorted:
            self._groups[group].sort()
        self._unsorted.clear()
        where, out = self._where[task], []
        for key in keys:
            found = where.get(key)
            if found is None:
                out.append("")
                continue
            group, rank = found
            order = self._groups[group]
            out.append(order[bisect.bisect_right(order, (rank, key)) % len(order)][1] if len(order) > 1 else "")
        return out

    def __len__(self) -> int:
        """Entries in the pools."""
        return sum(len(w) for w in self._where.values())

