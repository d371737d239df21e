"""Rows from outside checked one by one before they enter a cache (`illm cache import`, `illm cache
merge`): a shared annotation dataset becomes other runs' training targets, and its keys are hashes of
public inputs, so a row is let in only when it is what its key says it is.

A row passes when:
- its `model` names a model, and on import never an address or a key variable (no `@`, `#`, `://`
  or `HOST:PORT`: `ADDRESS`): a row's model is an identity, and a dataset from a stranger must not
  decide where a request goes or which secret rides with it (a merge takes caches from this disk,
  whose served models' rows keep the spec they were annotated through, "NAME@URL": adopting one
  reads its served name only, `illm_tools.tasks.annotation_setup`);
- it holds its task's answer: a ranking row its candidates (at least one) with their scores and
  `chosen_index`, a text row its text and an embedding of `embedding_dim` >= 1 values (a row
  without one would be looked up as found, with NaN targets);
- its key is recomputed from its own columns (`row_keys`: the task, its template and version, the
  renderer, the model fingerprint, the decoding parameters, the prompt and the candidates, exactly
  as `PromptBuilder.key` makes it, under each layout whose template could have rendered the prompt)
  and equals the stored one: a row edited under its old key is refused;
- a ranking row's lists agree (one log-prob sum, token count, neutral sum and per-token list per
  candidate; each count the length of its token list and at least 1; each sum the sum of its
  tokens within `SUM_TOLERANCE`), every log-prob is finite and at most 0, and `chosen_index` names a candidate
  (the highest sum, as the annotator chooses it);
- a text row's embedding is finite, of the length its `embedding_dim` says, and of its model's
  width (that of the model's rows in the cache; for a model new to the cache, the width most of
  its rows in the batch have).
A row whose key the cache holds with other content (`CONTENT`) is not written either: the first
writer of a key wins, and the difference is counted and shown. Bad rows are left out and the good
ones enter (the command prints how many were refused and why, with the first keys).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

SUM_TOLERANCE = 1e-3
"""How far a candidate's stored sum may be from the sum of its stored token log-probs (float32 rounding)."""
ADDRESS = re.compile(r"[@#]|://|^//|(?:localhost|[\w-]+(?:\.[\w-]+)+|\[[0-9A-Fa-f:.]*\]):\d{1,5}(?![\w.])")
"""What in a row's `model` names where a request would go or which secret it carries: an openai
spec's `NAME@URL#VAR` parts, any URL, a `HOST:PORT` whose host is `localhost`, dotted or an IPv6
literal (a model's name holds none of them; the stub's `stub:16` and the oracle's
`oracle:noise=0.5` are names)."""
CONTENT = ("task", "prompt", "candidates", "chosen_index", "text")
"""The columns that make two rows under one key the same answer (log-probs and embeddings aside:
two honest annotators in bf16 differ there by rounding)."""


@dataclass
class Checked:
    """What a check of incoming rows found."""

    refused: list[tuple[str, str]] = field(default_factory=list)
    """(key, reason) of each row left out, in the order met."""
    conflicts: list[str] = field(default_factory=list)
    """Keys the cache already holds with other content (not written: the cache's row stays)."""

    def reasons(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for _, why in self.refused:
            out[why] = out.get(why, 0) + 1
        return out


def row_keys(row: dict) -> set[str]:
    """The keys `row`'s own columns give, one per layout whose template (at the row's template
    version) could have rendered its prompt; empty when none can (another template or task)."""
    from illm_tools.keys import make_key
    from illm_tools.tasks.prompts import layouts_of
    from illm_tools.tasks.registry import get_task

    try:
        spec = get_task(row["task"])
        decoding = json.loads(row["decoding"])
    except Exception:  # noqa: BLE001 - a task this illm lacks, or decoding that is not JSON: no key to give
        return set()
    candidates = [" " + c for c in row["candidates"] or ()] if spec.kind == "ranking" else None
    keys = set()
    for layout in layouts_of(row["task"], row["prompt"] or ""):
        template, version = spec.templates[layout]
        if version != row["template_version"]:
            continue
        setup = make_key(task=row["task"], template=template, template_version=version, renderer=row["renderer"],
                         model_fingerprint=row["model_fingerprint"], decoding=decoding)
        keys.add(make_key(setup=setup, prompt=row["prompt"], candidates=candidates))
    return keys


def _finite(values: Iterable) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


def row_problem(row: dict, dims: dict[str, int], addresses: bool = False) -> str | None:
    """Why `row` may not enter a cache (one short reason), or None; `dims`: the embedding width of each
    model fingerprint met so far (a text row's is added)."""
    why = model_problem(row["model"], addresses)
    if why is not None:
        return why
    if row["key"] not in row_keys(row):
        return "its key is not the one its own columns give"
    from illm_tools.tasks.registry import get_task

    spec = get_task(row["task"])  # row_keys gave a key: a task this illm has
    if spec.kind == "ranking":
        cands = row["candidates"] or []
        lists = [row[c] for c in ("cand_logprob_sum", "cand_token_count", "cand_token_logprobs", "neutral_logprob_sum")]
        if all(v is None for v in lists) and row["chosen_index"] is None:
            return "it holds no answer (no scores)"
        if any(v is None or len(v) != len(cands) for v in lists) or not cands:
            return "its candidates' scores do not match its candidates"
        sums, counts, tokens, neutral = lists
        if not all(_finite(t) for t in tokens) or not _finite(sums) or not _finite(neutral):
            return "a log-prob is not a finite number"
        if any(v > 0 for t in tokens for v in t) or any(s > 0 for s in sums):
            return "a log-prob is above 0"
        if any(n != len(t) or n < 1 for n, t in zip(counts, tokens)) or \
                any(abs(s - math.fsum(t)) > SUM_TOLERANCE * max(1.0, len(t)) for s, t in zip(sums, tokens)):
            return "its sums or token counts do not match its token log-probs"
        chosen = row["chosen_index"]
        if not isinstance(chosen, int) or not 0 <= chosen < len(cands) or sums[chosen] < max(sums):
            return "chosen_index is not its best candidate"
    else:
        if row["text"] is None or (row["embedding"] is None and row["embedding_dim"] is None):
            return "it holds no answer (no text or embedding)"
        emb, dim = row["embedding"] or [], row["embedding_dim"]
        if dim is None or dim < 1 or len(emb) != dim or not _finite(emb):
            return "its embedding is not finite numbers of its stated dimension"
        if spec.parse is not None and row["candidates"] is None:
            return "it holds no parse of its text (candidates)"
        if dims.setdefault(row["model_fingerprint"], dim) != dim:
            return f"its embedding has {dim} dimensions, its model's others {dims[row['model_fingerprint']]}"
    return None


def model_problem(model, addresses: bool = False) -> str | None:
    """Why a row's `model` is not a model's name (one short reason), or None; `addresses`: a served
    model's spec with its address passes (a merge's)."""
    if not isinstance(model, str) or not model.strip():
        return "it names no model"
    if not addresses and (":" in model or "@" in model or "#" in model or model.startswith("//")) \
            and ADDRESS.search(model):  # each part of ADDRESS holds one of these
        return "its model names an address or a key variable"
    return None


def model_dims(cache) -> dict[str, int]:
    """The embedding width of each model fingerprint a cache's rows hold."""
    table = cache.table(["model_fingerprint", "embedding_dim"])
    return {f: d for f, d in zip(table.column("model_fingerprint").to_pylist(), table.column("embedding_dim").to_pylist())
            if d is not None}


def check_rows(table, cache, dims: dict[str, int], found: Checked, addresses: bool = False):
    """`table` (annotation rows, a pyarrow Table) without the rows that may not enter `cache`: each
    refused row's key and reason, and each key the cache holds with other content, go to `found`.
    `addresses`: let a row's model name a served model's address (a merge of this disk's caches;
    never an import)."""
    import pyarrow as pa

    rows = table.to_pylist()
    votes: dict[str, dict[int, int]] = {}  # a model the cache has no rows of: the width most of its rows here have
    for r in rows:
        if r["embedding_dim"] is not None and r["model_fingerprint"] not in dims:
            count = votes.setdefault(r["model_fingerprint"], {})
            count[r["embedding_dim"]] = count.get(r["embedding_dim"], 0) + 1
    dims.update({f: max(count, key=count.get) for f, count in votes.items()})
    keep = []
    present = cache.lookup([r["key"] for r in rows])
    for i, row in enumerate(rows):
        why = row_problem(row, dims, addresses)
        if why is not None:
            found.refused.append((row["key"], why))
            continue
        held = present.get(row["key"])
        if held is not None and any(held[c] != row[c] for c in CONTENT):
            found.conflicts.append(row["key"])
            continue
        keep.append(i)
    return table.take(pa.array(keep, type=pa.int64())) if len(keep) < len(rows) else table


def summary(found: Checked, first: int = 3) -> Sequence[str]:
    """The lines a command prints of what it left out (none when nothing)."""
    lines = []
    if found.refused:
        why = "; ".join(f"{n:,} {reason}" for reason, n in found.reasons().items())
        keys = ", ".join(k[:12] for k, _ in found.refused[:first])
        lines.append(f"refused {len(found.refused):,} rows ({why}); first keys {keys}")
    if found.conflicts:
        keys = ", ".join(k[:12] for k in found.conflicts[:first])
        lines.append(f"kept the cache's own row for {len(found.conflicts):,} keys it holds with another answer; "
                     f"first keys {keys}")
    return lines


def shareable(table):
    """A shard's rows as a shared file holds them: a served model's spec written by this machine's
    annotator ("NAME@URL#VAR") as its address-free identity ("openai:NAME", `openai_wire.identity`),
    so the file names no engine and no key variable (an import refuses those) and another user's
    `illm train --cache` reaches the model at their own --endpoint. The keys are unchanged: a served
    model's key holds its fingerprint, never its address."""
    import pyarrow as pa

    from illm_tools.llm.openai_wire import address_of, describe_offline, identity

    models = table.column("model").to_pylist()
    named = {m: identity(m) for m in set(models) if m and describe_offline(m) is not None and address_of(m)}
    if not named:
        return table
    column = pa.array([named.get(m, m) for m in models], type=table.schema.field("model").type)
    return table.set_column(table.schema.get_field_index("model"), "model", column)
