"""A stand-in for the LLM where its answers do not matter: benchmarks of the trainer's speed and
tests of the target plumbing. `SyntheticLM` carries only a model's identity (fingerprint, hidden
size); `SyntheticAnnotator` writes rows of the real annotation schema whose numbers derive from
each key (deterministic, no LLM), through the real `Annotator` (plans, chunks, cache writes)."""

from __future__ import annotations

import hashlib
from types import SimpleNamespace

import numpy as np

from illm_tools.annotate.engine import Annotator


class SyntheticLM:
    """A model's identity without weights: `fingerprint` (as keys hash it) and `hidden_size`."""

    def __init__(self, name: str = "synthetic", hidden_size: int = 576):
        self.fingerprint = {"model_id": name, "source": "local", "sha256": None, "revision": None,
                            "dtype": "bfloat16", "quant": "none"}
        self.hidden_size = hidden_size


class SyntheticAnnotator(Annotator):
    """Writes rows of the real schema whose numbers derive from the key (no LLM): two token
    log-probs per candidate, an 8-token "summary" with an embedding of the model's hidden size."""

    def neutral_scores(self, candidates):
        return [-float(len(c)) for c in candidates]

    def annotate(self, states):
        rows = []
        for jobs in states:
            for job in jobs:
                rng = np.random.default_rng(int(hashlib.sha256(job.key.encode()).hexdigest()[:8], 16))
                if job.prompt.task == "action":
                    n = len(job.prompt.candidates)
                    tokens = [list(rng.normal(-2, 1, size=2)) for _ in range(n)]
                    scores = SimpleNamespace(token_logprobs=tokens, token_counts=[2] * n,
                                             sums=[float(sum(t)) for t in tokens])
                    rows.append(self._action_row(job, scores))
                else:
                    gen = SimpleNamespace(text="synthetic", token_ids=[0] * 8,
                                          embedding=rng.normal(size=self.lm.hidden_size).astype(np.float32))
                    rows.append(self._summary_row(job, gen))
        return rows
