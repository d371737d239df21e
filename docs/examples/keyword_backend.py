"""An LLM backend as an illm plug-in: `illm annotate DATA --backend keywords`.

A toy that needs no weights: it ranks each valid action by how many of its words the prompt's last
line holds, writes that line back as its "summary", and embeds a text as a hashed bag of words. A
real backend (a model server, a library of your own) keeps the same shape: a class with `load`,
`model_fingerprint` (what every cache key of its answers hashes: change it when the answers
change) and `model_hidden_size`, and the `Backend` protocol's `score`, `generate`,
`score_and_generate` and `embed`. tests/test_docs_examples.py annotates and trains with it.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.llm.generation import Generation
from illm_tools.llm.scoring import CandidateScores

WIDTH = 64
HOP = "the keywords backend reads text: use --mode obs, or --backend transformers for hop"


def _last_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else ""


class KeywordBackend:
    name = "keywords"
    device = "cpu"
    default_model = "keywords"
    shares_prefix = False  # the engine need not send the two tasks' shared prompt prefix once
    computes = False  # no dtype to choose: --dtype auto measures nothing

    def __init__(self, model: str = "keywords"):
        self.model = model
        self.hidden_size = WIDTH
        self.fingerprint = self.model_fingerprint(model)

    @classmethod
    def load(cls, model: str = "keywords", *, dtype: str = "float32", quant: str = "none", device: str = "cpu",
             cache_dir=None) -> KeywordBackend:
        return cls(model)

    @staticmethod
    def model_fingerprint(model: str, *, dtype: str = "float32", quant: str = "none") -> dict:
        return {"model_id": model, "source": "keywords", "sha256": None, "revision": "1", "dtype": "float32",
                "quant": "none"}

    @staticmethod
    def model_hidden_size(model: str) -> int:
        return WIDTH

    @staticmethod
    def check_use(env_id: str, renderer: str) -> None:
        """Refuse in one line what it cannot read: iLLM(hop)'s states are embeddings, not text."""
        if renderer.startswith("hop@"):
            raise UsageError(HOP)

    # --- the protocol -----------------------------------------------------------------------------
    def score(self, contexts, candidates, *, batch_size: int = 8):
        """Per state, log P(candidate | context): here a softmax over the candidates' word overlaps."""
        out = []
        for context, cands in zip(contexts, candidates):
            seen = set(_last_line(context).lower().split())
            hits = [sum(word in seen for word in c.lower().split()) for c in cands]
            norm = math.log(sum(math.exp(h) for h in hits))
            out.append(CandidateScores.from_logprobs([[h - norm] for h in hits]))  # one "token" each
        return out

    def generate(self, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        """Greedy continuations with their embeddings: here the prompt's last line, cut to the limit."""
        out = []
        for prompt in prompts:
            words = _last_line(prompt).split()[:max_new_tokens]
            text = " ".join(words)
            out.append(Generation(text, list(range(len(words))), True, self.embed([text])[0]))
        return out

    def score_and_generate(self, contexts, candidates, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        return self.score(contexts, candidates), self.generate(prompts, max_new_tokens=max_new_tokens)

    def embed(self, texts, *, batch_size: int = 8):
        """[n, WIDTH] float32: each word adds 1 at a position its hash picks; rows have unit length."""
        rows = np.zeros((len(texts), WIDTH), np.float32)
        for i, text in enumerate(texts):
            for word in text.lower().split():
                rows[i, int(hashlib.sha256(word.encode()).hexdigest(), 16) % WIDTH] += 1.0
        return rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-6)

    # --- iLLM(hop): prompts with input embeddings spliced in; this backend has none -----------------
    def _no_hop(self, *args, **kwargs):
        raise UsageError(HOP)

    input_embeddings = last_hidden = spliced = _no_hop  # every member of the protocol must exist
