"""Cache keys: stable across processes, independent of dict order, sensitive to every input,
and never built from Python objects."""

from __future__ import annotations

import copy
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from illm_tools.keys import canonical_json, fingerprint_hash, make_key

REPO = Path(__file__).resolve().parents[1]

INPUTS = dict(
    task="action",
    template_version=1,
    renderer="babyai-text@1",
    decoding={"temperature": 0.0, "max_new_tokens": 64},
    prompt="Goal: go to the red ball. é",
    candidates=["turn left", "go forward"],
    history_len=3,
    neutral=None,
    calibrate=True,
)
# Hard-coded: if this changes, every cache ever written is silently invalidated.
EXPECTED_KEY = "43fc97d0015486401e5ddf8c61e0ff43d234d1bfa4bde3a076104258718fe478"
FINGERPRINT = {"id": "HuggingFaceTB/SmolLM2-135M-Instruct", "revision": None, "dtype": "bfloat16", "quant": "q4_1"}
EXPECTED_FINGERPRINT = "44a709ed3fefe65cfaf0462443a23f21d6bf4cbf174da4686ffd6a645af0f92f"


def test_key_is_the_hard_coded_digest_in_this_process():
    assert make_key(**INPUTS) == EXPECTED_KEY
    assert fingerprint_hash(FINGERPRINT) == EXPECTED_FINGERPRINT


def test_key_is_the_same_in_a_fresh_process_with_another_hash_seed():
    code = (
        "from illm_tools.keys import make_key, fingerprint_hash;"
        f"print(make_key(**{INPUTS!r}));print(fingerprint_hash({FINGERPRINT!r}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True,
        env={"PYTHONHASHSEED": "12345", "PATH": ""},
    ).stdout.split()
    assert out == [EXPECTED_KEY, EXPECTED_FINGERPRINT]


def test_key_ignores_dict_and_argument_order():
    reordered = {k: INPUTS[k] for k in reversed(list(INPUTS))}
    reordered["decoding"] = {"max_new_tokens": 64, "temperature": 0.0}
    assert make_key(**reordered) == EXPECTED_KEY


def _mutations(value):
    """Values that differ from ``value`` in one small way each."""
    if isinstance(value, bool):
        return [not value, int(value), None]
    if isinstance(value, int):
        return [value + 1, float(value), str(value)]
    if isinstance(value, float):
        return [value + 1e-9, -0.0 if value == 0 else 0.0, int(value)]
    if isinstance(value, str):
        return [value + " ", value.upper(), value[:-1]]
    if isinstance(value, list):
        return [list(reversed(value)), value[:-1], [*value, value[0]]]
    if isinstance(value, dict):
        out = []
        for k, v in value.items():
            for m in _mutations(v):
                out.append({**value, k: m})
        return [*out, {**value, "extra": 1}]
    if value is None:
        return [0, "", False]
    raise AssertionError(value)


@pytest.mark.parametrize("name", list(INPUTS))
def test_key_changes_with_every_input(name):
    keys = {EXPECTED_KEY}
    for mutated in _mutations(INPUTS[name]):
        changed = copy.deepcopy(INPUTS)
        changed[name] = mutated
        keys.add(make_key(**changed))
    dropped = {k: v for k, v in INPUTS.items() if k != name}
    keys.add(make_key(**dropped))
    assert len(keys) == len(_mutations(INPUTS[name])) + 2


def test_renaming_an_input_changes_the_key():
    renamed = dict(INPUTS)
    renamed["prompt_text"] = renamed.pop("prompt")
    assert make_key(**renamed) != EXPECTED_KEY


@pytest.mark.parametrize(
    "bad",
    [(1, 2), {1, 2}, b"bytes", np.float32(0.5), np.int64(3), Fraction(1, 3), object(), len, {1: "int key"}],
    ids=["tuple", "set", "bytes", "np.float32", "np.int64", "Fraction", "object", "function", "int-dict-key"],
)
def test_non_plain_values_are_refused(bad):
    with pytest.raises(TypeError):
        make_key(task="action", value=bad)
    with pytest.raises(TypeError):
        make_key(task="action", nested={"deep": [bad]})


def test_non_finite_floats_are_refused():
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError):
            make_key(x=bad)


def test_canonical_json_is_compact_sorted_and_keeps_unicode():
    assert canonical_json({"b": [1, 0.1, None], "a": "é"}) == '{"a":"é","b":[1,0.1,null]}'
    assert canonical_json({"x": 1e-300}) == '{"x":1e-300}'


def test_fingerprint_hash_takes_only_a_dict_and_differs_from_make_key():
    with pytest.raises(TypeError):
        fingerprint_hash(["not", "a", "dict"])
    assert fingerprint_hash({"a": 1}) != make_key(a=1)
    assert fingerprint_hash({"a": 1, "b": 2}) == fingerprint_hash({"b": 2, "a": 1})


def test_make_key_needs_inputs():
    with pytest.raises(TypeError):
        make_key()


@pytest.mark.parametrize("text", ["plain", "", "é ünïcode 中文 \U0001f600", 'quote " backslash \\ slash /',
                                  "controls \n\t\r\x00\x1f\x7f \u2028\u2029", "lone surrogate \ud800"])
def test_a_state_keys_direct_json_is_byte_for_byte_json_dumps(text):
    """The keys of every step (setup digest, prompt, candidates) are written without json.dumps
    (keys.py `_flat_json`); what they hash must be exactly what json.dumps writes, or the trainer's
    keys would miss every row `illm annotate` wrote."""
    import json

    for value in ({"setup": "a" * 64, "prompt": text, "candidates": [" " + text, "go forward", ""]},
                  {"setup": text, "prompt": text, "candidates": None}, {text: [], "b": text}, {}):
        expected = json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
        assert canonical_json(value) == expected
    with pytest.raises(TypeError):  # not plain data: still refused, by the general path
        canonical_json({"prompt": text, "candidates": ("a", "b")})
    with pytest.raises(TypeError):
        canonical_json({1: text, "b": text})
