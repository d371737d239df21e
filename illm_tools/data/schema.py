"""Schema checks for datasets on disk: what kind and version a file holds, and refusal of the rest."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

import schemas
from illm_tools.errors import SchemaError


def kind_and_version(schema: pa.Schema) -> tuple[str | None, int | None]:
    """The (kind, version) stamped into an Arrow schema's metadata, or (None, None)."""
    meta = schema.metadata or {}
    kind = meta.get(schemas.KIND_KEY)
    version = meta.get(schemas.VERSION_KEY)
    return (kind.decode() if kind else None, int(version) if version else None)


def check(schema: pa.Schema, kind: str, where: str | Path) -> schemas.SchemaDef:
    """Return the schema definition a file was written with, or raise a SchemaError saying
    what was found and what is supported."""
    supported = schemas.available().get(kind, [])
    found_kind, found_version = kind_and_version(schema)
    wanted = f"{kind} schema version {', '.join(map(str, supported))}"
    if found_kind is None:
        raise SchemaError(f"{where} is not an illm dataset (no illm.kind in its Arrow metadata); expected {wanted}")
    if found_kind != kind:
        raise SchemaError(f"{where} holds a {found_kind} dataset (v{found_version}); expected {wanted}")
    if found_version not in supported:
        raise SchemaError(
            f"{where} is {kind} schema version {found_version}; this illm supports {wanted}: upgrade illm"
        )
    definition = schemas.load(kind, found_version)
    missing = set(definition.names) - set(schema.names)
    if missing:
        raise SchemaError(f"{where} lacks columns {sorted(missing)} of {kind} v{found_version}: re-create it")
    return definition
