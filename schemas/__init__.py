"""Versioned Arrow schemas: the single source of truth for every dataset illm writes.

Each schema is a JSON file ``<kind>.v<version>.json`` beside this module. Writers build their
Arrow schema from it and stamp ``illm.kind`` / ``illm.version`` into the Arrow metadata; readers
load the same file to check what they were given (see ``illm_tools.data.schema``).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import pyarrow as pa

HERE = Path(__file__).resolve().parent
KIND_KEY = b"illm.kind"
VERSION_KEY = b"illm.version"

_SCALARS = {
    "int8": pa.int8(),
    "int32": pa.int32(),
    "int64": pa.int64(),
    "float32": pa.float32(),
    "float64": pa.float64(),
    "bool": pa.bool_(),
    "string": pa.string(),
    "binary": pa.binary(),
}


def arrow_type(spec: str) -> pa.DataType:
    """Parse a type string of the schema files: a scalar name or ``list<...>`` nested."""
    spec = spec.strip()
    m = re.fullmatch(r"list<(.+)>", spec)
    if m:
        return pa.list_(arrow_type(m.group(1)))
    if spec not in _SCALARS:
        raise ValueError(f"unknown type {spec!r} in a schema file")
    return _SCALARS[spec]


@dataclass(frozen=True)
class SchemaDef:
    kind: str
    version: int
    description: str
    fields: tuple[dict, ...]

    @property
    def arrow(self) -> pa.Schema:
        """The Arrow schema, with kind and version stamped in its metadata."""
        fields = [
            pa.field(f["name"], arrow_type(f["type"]), nullable=f.get("nullable", False))
            for f in self.fields
        ]
        return pa.schema(
            fields, metadata={KIND_KEY: self.kind.encode(), VERSION_KEY: str(self.version).encode()}
        )

    @property
    def names(self) -> list[str]:
        return [f["name"] for f in self.fields]


def available() -> dict[str, list[int]]:
    """Every kind with its supported versions, from the files present."""
    out: dict[str, list[int]] = {}
    for p in sorted(HERE.glob("*.v*.json")):
        kind, _, ver = p.stem.rpartition(".v")
        out.setdefault(kind, []).append(int(ver))
    return {k: sorted(v) for k, v in out.items()}


@lru_cache(maxsize=None)
def load(kind: str, version: int | None = None) -> SchemaDef:
    """Load a schema definition; ``version=None`` means the newest one."""
    versions = available().get(kind)
    if not versions:
        raise ValueError(f"no schema of kind {kind!r}; known kinds: {sorted(available())}")
    version = versions[-1] if version is None else version
    if version not in versions:
        raise ValueError(f"{kind} schema version {version} is not one of {versions}")
    raw = json.loads((HERE / f"{kind}.v{version}.json").read_text())
    return SchemaDef(raw["kind"], int(raw["version"]), raw.get("description", ""), tuple(raw["fields"]))
