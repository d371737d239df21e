"""`KEY=VALUE` settings from the command line (`--bonus-option`, `--network-option`,
`--env-option`), parsed in one place; the owner of each setting checks names and types."""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any

from illm_tools.errors import UsageError


def parse_pairs(values: Iterable[str] | None, option: str) -> dict[str, Any]:
    """Repeated KEY=VALUE strings as a dict; values that read as JSON numbers or booleans are
    converted (`num_dists=4`), the rest stay strings (the owner of the option checks them)."""
    out: dict[str, Any] = {}
    for value in values or []:
        key, sep, rest = value.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"{option} takes KEY=VALUE, got {value!r}")
        rest = rest.strip()
        try:
            parsed = json.loads(rest)
            out[key.strip()] = parsed if isinstance(parsed, (int, float, bool)) else rest
        except ValueError:
            out[key.strip()] = rest
    return out
