"""One iLLM(hop) prompt: text with a window of input embeddings spliced in where the written history
would stand (`illm_tools.llm.backend`'s `spliced` call takes these)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class SplicedPrompt:
    """One hop prompt: text before the history, the window's input embeddings [L, d] (a tensor),
    text after it; `candidates` to score (the action task) or None (the summary: generate)."""

    head: str
    window: Any
    tail: str
    candidates: tuple[str, ...] | None = None
