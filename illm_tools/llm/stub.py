"""The stub backend: answers deterministically from the prompt, with no weights. For tests and
benchmarks of everything around the LLM (the cache, the engine's plans and chunks, the trainer's
targets and live fallback, the server), where what the LLM says does not matter, only that the
same prompt always gets the same answer and another prompt another one.

`--backend stub --model NAME`: NAME is free text naming the stand-in ("stub" by default; another
name is another model, so its answers get other keys); a trailing ":N" sets the hidden size
(`stub:64`; default 576, SmolLM2-135M's). Every number derives from sha256 of the prompt (and the
candidate): a candidate's two token log-probs, a summary's text ("stub <8 hex>"), 8 tokens and
its embedding; an input-embedding matrix of 256 rows for the Hopfield translation and Z_h as a
fixed random projection of a window's mean, both seeded by the name.
"""
from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np

from illm_tools.llm.spliced import SplicedPrompt

DEFAULT_HIDDEN = 576
STUB_VOCAB = 256


def _parse(model: str) -> tuple[str, int]:
    name, sep, size = model.partition(":")
    if sep and size.isdigit() and int(size) > 0:
        return name or "stub", int(size)
    return model or "stub", DEFAULT_HIDDEN


def _rng(*parts: str) -> np.random.Generator:
    digest = hashlib.sha256("\x00".join(parts).encode()).hexdigest()
    return np.random.default_rng(int(digest[:16], 16))


class StubBackend:
    name = "stub"
    device = "cpu"
    default_model = "stub"

    def __init__(self, model: str = "stub", *, dtype: str = "auto", quant: str = "none"):
        from illm_tools.llm.dtype import resolve_dtype

        self.model = model
        self.label, self.hidden_size = _parse(model)
        # it computes nothing, but stands in for a model that does: its keys carry the dtype a real
        # model would run in here, as `illm train --backend stub` resolves it
        self.fingerprint = self.model_fingerprint(model, dtype=resolve_dtype(dtype), quant=quant)
        self.shares_prefix = False

    @classmethod
    def load(cls, model: str, *, dtype: str = "auto", quant: str = "none", device: str = "cpu",
             cache_dir=None, batch_tokens=None) -> StubBackend:
        return cls(model, dtype=dtype, quant=quant)

    @staticmethod
    def model_fingerprint(model: str, *, dtype: str = "bfloat16", quant: str = "none") -> dict:
        return {"model_id": f"stub:{model}", "source": "stub", "sha256": None, "revision": "1", "dtype": dtype,
                "quant": quant}

    @staticmethod
    def model_hidden_size(model: str) -> int:
        return _parse(model)[1]

    # --- text ----------------------------------------------------------------------------------
    def _scores(self, context: str, candidates: Sequence[str]):
        from illm_tools.llm.scoring import CandidateScores

        return CandidateScores.from_logprobs([list(_rng(self.model, context, c).uniform(-6.0, -0.1, size=2))
                                              for c in candidates])

    def _generation(self, prompt: str):
        from illm_tools.llm.generation import Generation

        rng = _rng(self.model, "generate", prompt)
        text = f"stub {hashlib.sha256(prompt.encode()).hexdigest()[:8]}"
        return Generation(text, [0] * 8, True, rng.normal(size=self.hidden_size).astype(np.float32))

    def score(self, contexts, candidates, *, batch_size: int = 8):
        return [self._scores(c, cands) for c, cands in zip(contexts, candidates)]

    def generate(self, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        return [self._generation(p) for p in prompts]

    def score_and_generate(self, contexts, candidates, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        return self.score(contexts, candidates), self.generate(prompts)

    def embed(self, texts, *, batch_size: int = 8):
        return np.stack([_rng(self.model, "embed", t).normal(size=self.hidden_size).astype(np.float32)
                         for t in texts]) if len(texts) else np.zeros((0, self.hidden_size), np.float32)

    # --- input embeddings (iLLM(hop)) ------------------------------------------------------------
    def input_embeddings(self):
        import torch

        return torch.as_tensor(_rng(self.model, "vocab").normal(size=(STUB_VOCAB, self.hidden_size)),
                               dtype=torch.float32)

    def last_hidden(self, windows: Sequence):
        import torch

        weight = torch.as_tensor(_rng(self.model, "z_h").normal(size=(self.hidden_size, self.hidden_size)),
                                 dtype=torch.float32) / self.hidden_size ** 0.5
        if not len(windows):
            return torch.zeros(0, self.hidden_size)
        return torch.tanh(torch.stack([w.float().mean(0) for w in windows]) @ weight)

    def spliced(self, prompts: Sequence[SplicedPrompt], *, max_new_tokens: int = 64, batch_size: int = 8) -> list:
        out = []
        for p in prompts:
            window = np.round(np.asarray(p.window, dtype=np.float64), 5).tobytes().hex()
            text = f"{p.head}\x00{window}\x00{p.tail}"
            out.append(self._scores(text, p.candidates) if p.candidates is not None else self._generation(text))
        return out
