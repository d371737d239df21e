"""The checks of what an OpenAI-compatible engine answers (`illm_tools.llm.openai_wire` asks), before
anything is stored, each failure one line naming the engine's URL (`EndpointError`): one choice per
prompt, each index once (`ordered_choices`); a candidate's echoed tokens spelling the prompt that was
sent at their offsets (an engine echoing other tokens is refused), one run in increasing offsets, each
with a log-prob at most 0 and finite in float32, as is their sum (`candidate_logprobs`: a candidate
with no scored token would otherwise sum to 0 and win; the cache stores float32, where 1e39 is
infinite); a generated text a string (`generated_text`); an embedding of numbers, finite in float32
and of the width the engine gave at connection (`embedding_vectors`)."""

from __future__ import annotations

import math

import numpy as np

from illm_tools.llm.openai_wire import EndpointError

def ordered_choices(answer: dict, prompts: int, where: str) -> list[dict]:
    """The choices of a completions answer to `prompts` prompts, in prompt order; refused in one line
    naming `where` unless each index comes once."""
    choices = answer.get("choices")
    indices = [c.get("index") if isinstance(c, dict) else None for c in choices] if isinstance(choices, list) else []
    if not isinstance(choices, list) or sorted(i for i in indices if type(i) is int) != list(range(prompts)) \
            or len(indices) != prompts:
        raise EndpointError(f"{where} answered choices {indices[:8]} for {prompts} prompts "
                            "(each index once is expected): not used")
    return sorted(choices, key=lambda c: c["index"])


def _float32(values) -> np.ndarray | None:
    """`values` as float32, as the cache stores them, when each is a number (not a bool) finite there
    (1e39 is not); else None."""
    if not all(type(v) is float or type(v) is int for v in values):
        return None
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            array = np.asarray(values, dtype=np.float64).astype(np.float32)
    except OverflowError:  # an integer beyond any float
        return None
    return array if np.isfinite(array).all() else None


def candidate_logprobs(choice: dict, prompt: str, start: int, where: str) -> list[float]:
    """The log-probs of a choice's echoed tokens that end after the context (`start` characters of
    `prompt`): the echoed tokens spell `prompt`, the one sent, at their offsets (from 0, each where
    the one before ends); one run of consecutive tokens, in increasing offsets, each scored with a
    log-prob at most 0 and finite in float32, as is their sum (what the cache stores); else refused
    in one line naming `where` (a candidate with no scored token would sum to 0)."""
    lp = choice.get("logprobs") or {}
    if not isinstance(lp, dict):
        raise EndpointError(f"{where} answered log-probabilities that are not a JSON object: not used")
    offsets, logprobs, tokens = lp.get("text_offset"), lp.get("token_logprobs"), lp.get("tokens")
    if not offsets or logprobs is None:
        raise EndpointError(f"{where} gave no prompt log-probabilities (echo with logprobs): "
                            "this engine cannot rank candidates; vLLM can (docs/scale.md)")
    if not isinstance(offsets, list) or not isinstance(logprobs, list) or len(offsets) != len(logprobs) or \
            any(type(o) is not int for o in offsets) or any(b <= a for a, b in zip(offsets, offsets[1:])):
        raise EndpointError(f"{where} answered token offsets that are not increasing, one per log-prob: not used")
    ends = list(offsets[1:]) + [len(prompt) + 10**9]
    inside = [i for i in range(len(offsets)) if offsets[i] < len(prompt)]  # the echo, without a generated token
    echoed = [tokens[i] for i in inside] if isinstance(tokens, list) and len(tokens) == len(offsets) else None
    if echoed is None or not all(isinstance(t, str) for t in echoed) or "".join(echoed) != prompt or \
            any(offsets[i] != n for i, n in zip(inside, np.cumsum([0] + [len(t) for t in echoed[:-1]]).tolist())):
        raise EndpointError(f"{where} echoed tokens that do not spell the prompt it was sent at their offsets "
                            f"({prompt[:40]!r}...): not used")
    mine = [i for i in inside if ends[i] > start]
    if not mine or mine != list(range(mine[0], inside[-1] + 1)):
        raise EndpointError(f"{where} answered no contiguous tokens for a candidate ({prompt[start:][:40]!r}): not used")
    values = [logprobs[i] for i in mine]
    stored = _float32(values)
    if stored is None or any(v > 0 for v in values) or _float32([math.fsum(values)]) is None:
        raise EndpointError(f"{where} answered a candidate's token log-probs {values[:6]}, not all finite numbers "
                            "at most 0 (in float32, as the cache stores them, with their sum): not used")
    return [float(v) for v in values]


def generated_text(choice: dict, where: str) -> tuple[str, int, bool]:
    """(text, tokens generated, whether it finished) of a completion's choice; refused in one line
    naming `where` unless its text is a string (its log-probs, when given, an object)."""
    text, lp = choice.get("text", ""), choice.get("logprobs") or {}
    if not isinstance(text, str) or not isinstance(lp, dict):
        raise EndpointError(f"{where} answered a completion whose text is not a string: not used")
    tokens = lp.get("tokens")
    return text, len(tokens) if isinstance(tokens, list) else 0, choice.get("finish_reason") != "length"


def embedding_vectors(answer: dict, texts: int, width: int, where: str) -> list[np.ndarray]:
    """The embeddings of an answer to `texts` texts, in text order, as float32 vectors; refused in one
    line naming `where` unless each index comes once with a finite vector of `width` dimensions."""
    data = answer.get("data")
    indices = [d.get("index") if isinstance(d, dict) else None for d in data] if isinstance(data, list) else []
    if not isinstance(data, list) or len(data) != texts or any(type(i) is not int for i in indices) or \
            sorted(indices) != list(range(texts)):
        raise EndpointError(f"{where} answered {len(data) if isinstance(data, list) else 'no'} embeddings for "
                            f"{texts} texts (each index once is expected): not used")
    vectors = [d.get("embedding") for d in sorted(data, key=lambda d: d["index"])]
    stored = [_float32(v) if isinstance(v, list) and len(v) == width else None for v in vectors]
    if any(v is None for v in stored):
        raise EndpointError(f"{where} answered embeddings that are not finite vectors of {width} dimensions (finite "
                            "in float32, as the cache stores them; the width it gave when illm connected): not used")
    return stored
