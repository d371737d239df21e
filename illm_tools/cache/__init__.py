"""Annotation cache: content-addressed LLM annotations in append-only Arrow shards + a manifest.

``keys`` builds cache keys from named inputs, ``store.AnnotationCache`` reads and writes one cache
directory (``layout`` is its on-disk format, ``index`` its in-memory key index), ``tail.ShardTail``
reads every row once as the manifest grows (for a reader with an index of its own), ``verify`` checks
and merges whole caches. Nothing here imports the LLM, tasks or RL code.
"""

from illm_tools.keys import canonical_json, fingerprint_hash, make_key
from illm_tools.cache.store import AdoptReport, AnnotationCache
from illm_tools.cache.verify import MergeReport, VerifyReport, merge, verify

__all__ = [
    "AdoptReport",
    "AnnotationCache",
    "MergeReport",
    "VerifyReport",
    "canonical_json",
    "fingerprint_hash",
    "make_key",
    "merge",
    "verify",
]
