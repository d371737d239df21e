"""`illm cache show`: what the LLM answered for a few states of a cache, read-only.

A state is one (goal, history, observation) under one setup (renderer, model, history length); its
rows are one per language task. For each of the first `limit` states in the manifest's shard order:
its text, and per task the prompt the model was given with its answer: for a ranking task (action)
every candidate with its summed log-prob and token count, best first, and the one chosen; for a text
task (summary) the generated text. The cache is only read: shards are opened one at a time,
memory-mapped, without the embeddings; nothing is written, locked or repaired.
"""

from __future__ import annotations

from pathlib import Path

from illm_tools.cache import layout
from illm_tools.errors import CacheError, UsageError

STATE_COLUMNS = ("renderer", "model", "model_fingerprint", "history_len", "goal", "history", "observation")
"""The columns that say which state of which setup a row answers (the rest is the task's answer)."""
READ_COLUMNS = (*STATE_COLUMNS, "task", "prompt", "candidates", "cand_logprob_sum", "cand_token_count",
                "neutral_logprob_sum", "chosen_index", "text")


def _answer(row: dict) -> dict:
    """One task's answer: the prompt, and the ranking (best first) or the text."""
    out = {"task": row["task"], "prompt": row["prompt"]}
    if row["candidates"] is not None:
        sums, counts = row["cand_logprob_sum"] or [], row["cand_token_count"] or []
        neutral = row["neutral_logprob_sum"] or [None] * len(row["candidates"])
        ranking = [{"action": a, "logprob_sum": s, "tokens": n, "neutral_logprob_sum": z}
                   for a, s, n, z in zip(row["candidates"], sums, counts, neutral)]
        chosen = row["chosen_index"]
        out["chosen"] = row["candidates"][chosen] if chosen is not None and 0 <= chosen < len(ranking) else None
        out["ranking"] = sorted(ranking, key=lambda r: -r["logprob_sum"])
    if row["text"] is not None:
        out["text"] = row["text"]
    return out


def show(root: str | Path, limit: int = 3) -> list[dict]:
    """The first `limit` states of the cache at `root` with every task's answer (module docstring)."""
    root = Path(root)
    if limit <= 0:
        raise UsageError(f"--limit must be at least 1, got {limit}")
    if not (root / layout.MANIFEST).is_file():
        raise CacheError(f"no annotation cache at {root}: pass a folder `illm annotate --cache` wrote")
    states: dict[tuple, dict] = {}
    for entry in layout.read_manifest(root)["shards"]:
        table = layout.read_shard(root / entry["name"])
        for row in table.select(list(READ_COLUMNS)).to_pylist():
            key = tuple(row[c] for c in STATE_COLUMNS)
            if key not in states:
                if len(states) >= limit:
                    continue  # a later row may still answer another task of a state already shown
                states[key] = {**{c: row[c] for c in STATE_COLUMNS}, "answers": []}
            states[key]["answers"].append(_answer(row))
        if len(states) >= limit and all(len(s["answers"]) > 1 for s in states.values()):
            break
    return list(states.values())
