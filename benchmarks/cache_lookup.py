"""The trainer's cache look-up against the number of shards the cache holds, printed as a ratio to a
one-shard cache of the same rows, in the same run.

Live annotation writes a few states per shard (the async worker: 8), so a cache a run annotates as
it goes holds hundreds of small shards; each rollout looks up its 2,048 states' action and summary
rows (`CachedTargets`: two `get_matrices` calls, each with its task filter), the summaries'
embeddings `--dim` wide. Target: the 600-shard look-up within 10x the one-shard one. Measured on
a 2-core Xeon (AVX512-BF16, AMX) under a busy grid, 4-wide embeddings: 3.6x (26 ms against 7);
before the vectorised gather 51x (246 ms against 5). docs/measured.md has the figures since.

    .venv/bin/python benchmarks/cache_lookup.py [--rows 4800] [--shards 1 100 600] [--dim 576]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_cache_store import make_rows  # noqa: E402 - the tests' valid rows (action and summary)

from illm_tools.cache.store import AnnotationCache  # noqa: E402
from illm_tools.keys import make_key  # noqa: E402
from record import options, record, settings  # noqa: E402

ACTION = ["cand_logprob_sum", "cand_token_count", "neutral_logprob_sum"]


def widened(rows: list[dict], dim: int) -> list[dict]:
    """The rows with their embeddings `dim` wide (a model's hidden size), as the trainer reads them."""
    for row in rows:
        if row["embedding"] is not None:
            row["embedding"], row["embedding_dim"] = (row["embedding"] * dim)[:dim], dim
    return rows


def lookup_ms(rows: int, shards: int, keys: int = 2048, repeats: int = 5, dim: int = 576) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        writer, per = AnnotationCache(Path(tmp) / "ann"), rows // shards
        for s in range(shards):
            writer.write(widened(make_rows(s * per, (s + 1) * per), dim))
        wanted = [make_key(tag="t", i=int(i)) for i in np.random.default_rng(0).integers(0, per * shards, keys)]
        cache = AnnotationCache(Path(tmp) / "ann")
        start = time.perf_counter()
        for _ in range(repeats):
            cache.refresh()
            cache.get_matrices(wanted, ACTION, task="action")
            cache.get_matrices(wanted, ["embedding"], task="summary")
        return (time.perf_counter() - start) / repeats * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=4800)
    parser.add_argument("--shards", type=int, nargs="+", default=[1, 100, 600])
    parser.add_argument("--dim", type=int, default=576, help="Embedding width (SmolLM2-135M's: 576; Llama-3-8B's: 4096).")
    options(parser)
    args = parser.parse_args()
    base = None
    figures = {}
    print(f"{args.rows:,} rows, embeddings {args.dim} wide, 2,048 keys looked up per task")
    for shards in args.shards:
        ms = lookup_ms(args.rows, shards, dim=args.dim)
        base = base or ms
        figures[f"lookup_ms_{shards}_shards"] = ms
        print(f"{shards:5d} shards: {ms:7.1f} ms per rollout's look-up ({ms / base:5.1f}x one shard)")
    if not args.no_record:  # the headline: the most shards against the first (one shard by default)
        record("cache_lookup", figures, ratio={"name": f"{args.shards[-1]}-shard / {args.shards[0]}-shard look-up time",
                                               "value": ms / base, "target": 10.0, "direction": "at_most"},
               out=args.record, settings=settings(args))


if __name__ == "__main__":
    main()
