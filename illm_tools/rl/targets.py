"""LLM targets for training, read from the annotation cache, with a budgeted live fallback.

After each rollout the trainer hands every step's `StateRecord`. The keys are built by the same
`PromptBuilder` (renderer, templates, history length, model fingerprint) as `illm annotate`, so a
state annotated in bulk is a cache hit here. Distinct states the cache lacks are annotated by the
live LLM, at most `live_budget` per rollout, written back to the shared cache and used at once;
states still missing get no target (and so no bonus) and are counted.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from illm_tools.cache.store import AnnotationCache
from illm_tools.intrinsic.base import Targets
from illm_tools.tasks.calibration import action_distribution
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.state import StateRecord

ACTION_COLUMNS = ["cand_logprob_sum", "cand_token_count", "neutral_logprob_sum"]
_MEMO_LIMIT = 500_000


class CachedTargets:
    """`TargetProvider` over an `AnnotationCache`; `annotator` (an `illm_tools.annotate.engine.
    Annotator` over the same cache) enables the live fallback."""

    def __init__(self, cache: AnnotationCache, builder: PromptBuilder, *, calibration: str,
                 num_actions: int, embedding_dim: int, annotator=None, live_budget: int = 0):
        self.cache = cache
        self.builder = builder
        self.calibration = calibration
        self.num_actions = num_actions
        self.embedding_dim = embedding_dim
        self.annotator = annotator if live_budget > 0 else None
        self.live_budget = live_budget
        self._keys: dict[StateRecord, tuple[str, str]] = {}
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
        """Live fallback: the first `live_budget` distinct missing states, in rollout order."""
        missing = list(dict.fromkeys(r for r, f in zip(records, found) if not f))[: self.live_budget]
        if not missing:
            return 0
        b = self.builder
        plan = self.annotator.plan(missing, [b.env_id] * len(missing), [b.renderer] * len(missing))
        stats = self.annotator.run(plan)
        return stats.annotated_states

    def targets(self, records: Sequence[StateRecord]) -> Targets:
        self.cache.refresh()  # other runs may have written to the shared cache meanwhile
        keys_a, keys_s = self.keys(records)
        a, s, found = self._lookup(keys_a, keys_s)
        hits, live = int(found.sum()), 0
        if self.annotator is not None and not found.all():
            live = self._annotate_missing(records, found)
            a, s, found = self._lookup(keys_a, keys_s)
        b = len(records)
        probs = np.zeros((b, self.num_actions), np.float32)
        emb = np.zeros((b, self.embedding_dim), np.float32)
        idx = np.flatnonzero(found)
        if idx.size:
            scores = [np.asarray([a[c][i] for i in idx], dtype=np.float64) for c in ACTION_COLUMNS]
            probs[idx] = action_distribution(*scores, self.calibration)
            emb[idx] = s["embedding"][idx]
        n = max(b, 1)
        self._last = {"cache_hit_rate": hits / n, "target_coverage": idx.size / n, "live_annotations": float(live)}
        return Targets(probs, emb, found)

    def stats(self) -> Mapping[str, float]:
        """Of the last `targets` call (one rollout): share of steps found in the cache before the
        live fallback, share with a target after it, and states annotated live."""
        return dict(self._last)
