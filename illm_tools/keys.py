"""Cache keys: sha256 of the canonical JSON of named inputs, never of Python objects.

A key is built only from plain JSON values (str, int, float, bool, None, list, dict with str
keys). Anything else (tuples, numpy scalars, dataclasses, functions, ...) is refused with a
TypeError, so a key can never depend on an object's identity or pickling. The canonical form is
``json.dumps(sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)``;
floats are written with ``float.__repr__`` (shortest round-trip form, the same in every process).
A format tag is hashed in front, so changing the canonical form changes every key.
"""

from __future__ import annotations

import hashlib
import json
import math
from json.encoder import encode_basestring
from typing import Any

KEY_FORMAT = "illm.key.v1"
"""Tag hashed in front of the canonical JSON; bump it if the canonical form ever changes."""


def _plain(value: Any, path: str) -> Any:
    """Check ``value`` is plain JSON data (exact types: subclasses such as enums and numpy
    scalars are refused, since their JSON form differs between versions)."""
    if value is None or type(value) in (bool, int, str):
        return value
    if type(value) is float:
        if not math.isfinite(value):
            raise ValueError(f"{path}: non-finite float {value!r} cannot be part of a cache key")
        return value
    if type(value) is list:
        if all(type(v) is str for v in value):  # the common case (candidates): nothing to convert
            return value
        return [_plain(v, f"{path}[{i}]") for i, v in enumerate(value)]
    if type(value) is dict:
        out = {}
        for k, v in value.items():
            if type(k) is not str:
                raise TypeError(f"{path}: dict key {k!r} is {type(k).__name__}, not str")
            out[k] = _plain(v, f"{path}.{k}")
        return out
    raise TypeError(
        f"{path}: {type(value).__name__} cannot be part of a cache key; "
        "convert it to str/int/float/bool/None/list/dict first"
    )


def _flat_json(value: dict) -> str | None:
    """The canonical JSON of a dict of str keys whose values are str, None or lists of str (every
    state's key: setup digest, prompt, candidates), written directly, byte for byte what `json.dumps`
    writes (the tests compare them); None for anything else. Hand-written because the trainer keys
    two tasks of every step of every rollout, and `json.dumps`' checks and sorting were most of a
    key's cost."""
    if not all(type(k) is str for k in value):
        return None
    parts = []
    for k in sorted(value):
        v = value[k]
        if type(v) is str:
            text = encode_basestring(v)
        elif v is None:
            text = "null"
        elif type(v) is list and all(type(x) is str for x in v):
            text = "[" + ",".join(map(encode_basestring, v)) + "]"
        else:
            return None
        parts.append(encode_basestring(k) + ":" + text)
    return "{" + ",".join(parts) + "}"


def canonical_json(value: Any) -> str:
    """The canonical JSON text of plain data (see the module docstring)."""
    if type(value) is dict:
        flat = _flat_json(value)
        if flat is not None:
            return flat
    return json.dumps(
        _plain(value, "$"), sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    )


def key_text(value: Any) -> str:
    """What a key hashes: the format tag, a newline, the canonical JSON of `value`."""
    return f"{KEY_FORMAT}\n{canonical_json(value)}"


def _digest(value: Any) -> str:
    return hashlib.sha256(key_text(value).encode("utf-8")).hexdigest()


def make_key(**named_inputs: Any) -> str:
    """Hex sha256 of the named inputs that determine an annotation.

    Example: ``make_key(task="action", template_version=1, renderer="babyai-text@1",
    model_fingerprint=fp, decoding={...}, prompt=text, candidates=[...])``.
    """
    if not named_inputs:
        raise TypeError("make_key needs at least one named input")
    return _digest(named_inputs)


def fingerprint_hash(d: dict) -> str:
    """Hex sha256 of a fingerprint dict (e.g. a model's id, revision, dtype, quantisation)."""
    if type(d) is not dict:
        raise TypeError(f"fingerprint_hash takes a dict, got {type(d).__name__}")
    return _digest({"fingerprint": d})
