"""The LLM backend: model registry and loading, candidate scoring, greedy generation, embeddings.

Importing this package is cheap: torch and transformers are imported inside the functions that
need them. The transformers backend's calls are `score_candidates`, `generate` and
`score_and_generate` (the engine's one driver, `llm.driver`) and `embed_texts`; `extend` /
`score_continuations` expose the KV-cache step underneath them. The
protocol every backend implements is `illm_tools.llm.backend`.
"""

from illm_tools.llm.driver import generate, score_candidates
from illm_tools.llm.generation import Generation, embed_texts
from illm_tools.llm.loading import LoadedModel, cache_root, load_model
from illm_tools.llm.registry import DEFAULT_MODEL, ModelInfo, ModelSpec, list_models, resolve
from illm_tools.llm.scoring import CandidateScores, PrefixState, extend, score_continuations

__all__ = [
    "DEFAULT_MODEL", "CandidateScores", "Generation", "LoadedModel", "ModelInfo", "ModelSpec", "PrefixState",
    "cache_root", "embed_texts", "extend", "generate", "list_models", "load_model", "resolve",
    "score_candidates", "score_continuations",
]
