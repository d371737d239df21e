"""LLM targets for training, read from the annotation cache, with a live fallback.

After each rollout the trainer hands every step's `StateRecord`. The keys are built by the same
`PromptBuilder` (renderer, templates, history length, model fingerprint) as `illm annotate`, so a
state annotated in bulk is a cache hit here. The distinct states the cache lacks, most visited
over the run so far first, go to the live annotator (`illm_tools.rl.live`): `sync` annotates the
first `live_budget` of them now and this rollout uses them; `async` hands them to a worker
process and a later rollout finds its answers in the shared cache. States still missing get no
target (and so no bonus) and are counted. `check_setup` refuses a cache that holds annotations
but none for this run's setup.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence

import numpy as np

from illm_tools.cache.store import AnnotationCache
from illm_tools.intrinsic.base import Targets
from illm_tools.tasks.calibration import ACTION_TARGETS, action_target
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.state import StateRecord

ACTION_COLUMNS = ["cand_logprob_sum", "cand_token_count", "neutral_logprob_sum"]
_MEMO_LIMIT = 500_000


class CachedTargets:
    """`TargetProvider` over an `AnnotationCache`; `live` (`illm_tools.rl.live.SyncLive` or
    `AsyncLive`, writing to the same cache) enables the live fallback. `action_target`: f^a's target is the
    softmax of the calibrated scores (`distribution`) or the one-hot of their argmax (`argmax`,
    the paper's choice)."""

    def __init__(self, cache: AnnotationCache, builder: PromptBuilder, *, calibration: str,
                 num_actions: int, embedding_dim: int, action_target: str = "distribution", live=None):
        self.cache = cache
        self.builder = builder
        self.calibration = calibration
        if action_target not in ACTION_TARGETS:
            raise ValueError(f"unknown action target {action_target!r}: use one of {', '.join(ACTION_TARGETS)}")
        self.action_target = action_target
        self.num_actions = num_actions
        self.embedding_dim = embedding_dim
        self.live = live
        self._keys: dict[StateRecord, tuple[str, str]] = {}
        self._visits: Counter[StateRecord] = Counter()
        self._last: dict[str, float] = {"cache_hit_rate": 0.0, "target_coverage": 0.0, "live_annotations": 0.0}

    def keys(self, records: Sequence[StateRecord]) -> tuple[list[str], list[str]]:
        """(action keys, summary keys) of the records, memoised per distinct record."""
        if len(self._keys) > _MEMO_LIMIT:
            self._keys.clear()
        out_a, out_s = [], []
        for r in records:
            pair = self._keys.get(r)
            if pair is None:
                pair = self._keys[r] = self.builder.state_keys(r)
            out_a.append(pair[0])
            out_s.append(pair[1])
        return out_a, out_s

    def _lookup(self, keys_a: list[str], keys_s: list[str]) -> tuple[dict, dict, np.ndarray]:
        """One cache look-up per task: (action columns, summary columns, mask with both)."""
        a = self.cache.get_columns(keys_a, ACTION_COLUMNS, task="action")
        s = self.cache.get_columns(keys_s, ["embedding"], task="summary")
        return a, s, a["found"] & s["found"]

    def _annotate_missing(self, records: Sequence[StateRecord], found: np.ndarray) -> int:
        """Live fallback: the distinct missing states, most visited over the run so far first,
        go to the live annotator (`illm_tools.rl.live`); returns the states it annotated."""
        missing = list(dict.fromkeys(r for r, f in zip(records, found) if not f))
        missing.sort(key=self._visits.__getitem__, reverse=True)  # stable: ties in rollout order
        return self.live.submit(missing)

    def _count_visits(self, records: Sequence[StateRecord]) -> None:
        if len(self._visits) > _MEMO_LIMIT:  # keep the states seen more than once
            self._visits = Counter({r: n for r, n in self._visits.items() if n > 1})
        self._visits.update(records)

    def targets(self, records: Sequence[StateRecord]) -> Targets:
        self.cache.refresh()  # other runs may have written to the shared cache meanwhile
        keys_a, keys_s = self.keys(records)
        a, s, found = self._lookup(keys_a, keys_s)
        hits, live = int(found.sum()), 0
        if self.live is not None:
            self._count_visits(records)  # only the live fallback's priorities need them
            if not found.all():
                live = self._annotate_missing(records, found)
                if self.live.waits:  # sync: this rollout uses the new answers; async: a later one
                    a, s, found = self._lookup(keys_a, keys_s)
            live += self.live.landed()
        b = len(records)
        probs = np.zeros((b, self.num_actions), np.float32)
        emb = np.zeros((b, self.embedding_dim), np.float32)
        idx = np.flatnonzero(found)
        if idx.size:
            scores = [np.asarray([a[c][i] for i in idx], dtype=np.float64) for c in ACTION_COLUMNS]
            probs[idx] = action_target(*scores, self.calibration, self.action_target)
            emb[idx] = s["embedding"][idx]
        n = max(b, 1)
        self._last = {"cache_hit_rate": hits / n, "target_coverage": idx.size / n, "live_annotations": float(live),
                      **(self.live.stats() if self.live is not None else {})}
        return Targets(probs, emb, found)

    def stats(self) -> Mapping[str, float]:
        """Of the last `targets` call (one rollout): share of steps found in the cache before the
        live fallback, share with a target after it, states annotated live since the last call,
        and the live annotator's queue (`live_queue`: states waiting in the async worker)."""
        return dict(self._last)

    def close(self) -> None:
        """Stop the live annotator (the async worker process), if any."""
        if self.live is not None:
            self.live.close()


_FLAGS = {"history_len": "--history", "layout": "--layout", "renderer": "renderer", "template_version": "template version",
          "decoding": "decoding"}


def _describe(setup: dict, fields: list[str], model: str | None) -> str:
    """The differing settings of a setup as the flags that select them."""
    from illm_tools.llm.loading import model_options

    return ", ".join((model or model_options(setup["model"], setup["model_fingerprint"]))
                     if f == "model_fingerprint" else f"{_FLAGS[f]} {setup[f]}" for f in fields)


def check_setup(cache: AnnotationCache, builder: PromptBuilder, *, model: str, dtype: str, quant: str,
                tasks: Sequence[str] = ("action", "summary")) -> None:
    """Refuse a cache that holds annotations but none for this run's setup, in one line naming the
    settings that differ and what the cache holds ("the cache holds --history 0 annotations; this
    run asks for --history 3"). Nothing is refused when every task has entries of this setup."""
    from illm_tools.errors import CacheError
    from illm_tools.tasks.prompts import layouts_of

    held = cache.setups()
    for task in tasks:
        want = builder.setup(task)
        rows = [r for r in held if r["task"] == task]
        for r in rows:
            r["layouts"] = layouts_of(task, r["prompt"])

        def differs(r: dict) -> list[str]:
            out = [f for f in ("model_fingerprint", "history_len", "template_version", "renderer", "decoding")
                   if r[f] != want[f]]
            return out + (["layout"] if want["layout"] not in r["layouts"] else [])

        if any(not differs(r) for r in rows):
            continue
        if not rows:
            raise CacheError(f"the cache {cache.root} holds no {task} annotations, which this run needs: run "
                             f"`illm annotate DATA --cache {cache.root} --tasks action,summary`, or pass --new-setup "
                             "to let live annotation start them")
        closest = max(rows, key=lambda r: (-len(differs(r)), r["entries"]))
        fields = differs(closest)
        theirs = dict(closest, layout=closest["layouts"][0] if closest["layouts"] else "unknown")
        raise CacheError(
            f"the cache {cache.root} holds no {task} annotations for this run's setup: it holds "
            f"{_describe(theirs, fields, None)} annotations ({closest['entries']:,} entries); this run asks for "
            f"{_describe(want, fields, f'--model {model} --dtype {dtype} --quant {quant}')}. Train with the "
            "cache's settings, or pass --new-setup to start this setup in the cache")
