"""Trajectory datasets on disk: the sharded writer, the checked reader, and `data info`.

Layout is the one `datasets.Dataset.save_to_disk` writes, so `datasets.load_from_disk(DIR)` and
plain pyarrow read it with no illm code:

    DIR/data-00000.arrow ...   Arrow IPC stream shards (schema version in their metadata)
    DIR/dataset_info.json      Hugging Face features
    DIR/state.json             the list of shards; rewritten atomically, last

Each shard's entry in state.json also records its size, sha256 and row count (extra keys that
`datasets` ignores), so a shard cut short or with flipped bits is refused with one line naming it,
never read as other data; datasets written before these keys existed are read unchecked.
A dataset becomes visible whole: a new or overwritten dataset is written to a staging folder and
renamed into place at the end; appended shards are listed in state.json only once complete. A
crash leaves the old dataset as it was.
"""

from __future__ import annotations

import json
import os
import shutil
import time
import uuid
from collections.abc import Iterable
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc

import schemas
from illm_tools.data import schema as schema_check
from illm_tools.errors import DamagedFileError, OutputExistsError, UsageError
from illm_tools.folders import STATE  # the stage markers live with `folders`

KIND = "trajectory"

INFO = "dataset_info.json"


def _fsync_write(path: Path, text: str) -> None:
    from illm_tools import durable

    durable.write_text(path, text)


def _recollect(root: Path) -> str:
    return f"re-collect it (`illm collect ... --out {root} --overwrite`) or restore the folder from a copy"


def _shard_entries(root: Path) -> list[dict]:
    """state.json's shard entries ({"filename", and for checked datasets "illm_bytes",
    "illm_sha256", "illm_rows"}), refusing a state.json that is not what the writer wrote."""
    try:
        entries = json.loads((root / STATE).read_text())["_data_files"]
        if not all(isinstance(e, dict) and isinstance(e["filename"], str) for e in entries):
            raise TypeError("a shard entry lacks its file name")
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as e:
        raise DamagedFileError(f"{root / STATE} is damaged ({type(e).__name__}): {_recollect(root)}") from None
    return entries


def _shard_files(root: Path) -> list[str]:
    return [e["filename"] for e in _shard_entries(root)]


def _read_shard(root: Path, entry: dict) -> pa.Table:
    """One shard, checked against its state.json entry when it has one; damage -> one line."""
    from illm_tools.durable import sha256_file

    path = root / entry["filename"]
    if not path.is_file():
        raise DamagedFileError(f"trajectory shard {path} is listed in {STATE} but missing: {_recollect(root)}")
    if "illm_sha256" in entry and (path.stat().st_size != entry.get("illm_bytes")
                                   or sha256_file(path) != entry["illm_sha256"]):
        raise DamagedFileError(f"trajectory shard {path} is damaged (size or checksum differs from {STATE}): "
                               f"{_recollect(root)}")
    try:
        with pa.memory_map(str(path)) as source:
            table = pa.ipc.open_stream(source).read_all()
    except (OSError, pa.ArrowException) as e:
        raise DamagedFileError(f"trajectory shard {path} cannot be read ({str(e).splitlines()[0][:80]}): "
                               f"{_recollect(root)}") from None
    if "illm_rows" in entry and table.num_rows != entry["illm_rows"]:
        raise DamagedFileError(f"trajectory shard {path} has {table.num_rows} rows, {STATE} says "
                               f"{entry['illm_rows']}: {_recollect(root)}")
    return table


def _is_dataset(root: Path) -> bool:
    return (root / STATE).is_file()


class TrajectoryWriter:
    """Append steps column-wise; shards of `shard_rows` rows are written as they fill.

    mode: "new" refuses a folder that holds anything; "append" adds shards to an existing
    trajectory dataset; "overwrite" replaces it, but only once the new one is complete.
    """

    def __init__(self, out: str | Path, *, mode: str = "new", shard_rows: int = 50_000, part: dict | None = None):
        if mode not in ("new", "append", "overwrite"):
            raise UsageError(f"unknown write mode {mode!r}: use new, append or overwrite")
        self.out = Path(out)
        self.mode = mode
        self.shard_rows = shard_rows
        self.definition = schemas.load(KIND)
        self.arrow_schema = self._with_hf_features(self.definition.arrow)
        self._buffer: dict[str, list] = {name: [] for name in self.definition.names}
        self._new_files: list[str] = []
        self._entries: dict[str, dict] = {}  # shard name -> its state.json entry
        self.part = part
        """The settings of the collection writing these shards (env, action space, distractors, seeds,
        policy), recorded with each of them so `data info` can show each part of a dataset."""
        self.rows_written = 0
        self.first_episode_id = 0

        exists = self.out.exists() and any(self.out.iterdir())
        if exists and mode == "new":
            raise OutputExistsError(
                f"{self.out} already holds data: pass --append to add to it or --overwrite to replace it"
            )
        if mode == "append" and exists:
            if not _is_dataset(self.out):
                raise OutputExistsError(f"{self.out} holds files but no illm trajectory dataset: choose another --out")
            open_table(self.out, columns=["episode_id"])  # refuses another kind or version
            old = _shard_entries(self.out)
            self._old_files = [e["filename"] for e in old]
            self._entries.update({e["filename"]: e for e in old})
            self.first_episode_id = self._next_episode_id()
            self.workdir = self.out
        else:
            if mode == "overwrite" and exists and not _is_dataset(self.out):
                raise OutputExistsError(
                    f"{self.out} holds files that are not an illm trajectory dataset: refusing to overwrite them"
                )
            self._old_files = []
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.workdir = self.out.parent / f".{self.out.name}.staging-{uuid.uuid4().hex[:8]}"
            self.workdir.mkdir()

    @staticmethod
    def _with_hf_features(arrow_schema: pa.Schema) -> pa.Schema:
        import datasets  # lazily: heavy import

        features = datasets.Features.from_arrow_schema(arrow_schema)
        meta = dict(arrow_schema.metadata)
        meta[b"huggingface"] = json.dumps({"info": {"features": features.to_dict()}}).encode()
        return arrow_schema.with_metadata(meta)

    def _next_episode_id(self) -> int:
        table = open_table(self.out, columns=["episode_id"])
        if table.num_rows == 0:
            return 0
        return int(pc.max(table["episode_id"]).as_py()) + 1

    def add(self, columns: dict[str, Iterable]) -> None:
        """Add rows given as a dict of equal-length column sequences (all schema columns)."""
        missing = set(self._buffer) - set(columns)
        if missing:
            raise ValueError(f"rows lack columns {sorted(missing)}")
        for name, values in columns.items():
            self._buffer[name].extend(values)
        while len(self._buffer["episode_id"]) >= self.shard_rows:
            self._flush(self.shard_rows)

    def _flush(self, limit: int | None = None) -> None:
        n = min(len(self._buffer["episode_id"]), limit or self.shard_rows)
        if n == 0:
            return
        head = {k: v[:n] for k, v in self._buffer.items()}
        batch = pa.RecordBatch.from_pydict(head, schema=self.arrow_schema)
        index = len(self._old_files) + len(self._new_files)
        name = f"data-{index:05d}-{uuid.uuid4().hex[:6]}.arrow"
        from illm_tools import durable
        from illm_tools.durable import sha256_file

        with durable.staged(self.workdir / name) as fh, pa.ipc.new_stream(fh, self.arrow_schema) as writer:
            writer.write_batch(batch)
        tmp = Path(fh.name)
        self._entries[name] = {"filename": name, "illm_bytes": tmp.stat().st_size, "illm_sha256": sha256_file(tmp),
                               "illm_rows": n, **({"illm_part": self.part} if self.part else {})}
        durable.commit(tmp, self.workdir / name)
        self._new_files.append(name)
        self.rows_written += n
        self._buffer = {k: v[n:] for k, v in self._buffer.items()}

    def close(self) -> Path:
        """Write the last shards and the state; make the dataset visible. Returns its folder."""
        while self._buffer["episode_id"]:
            self._flush()
        import datasets

        features = datasets.Features.from_arrow_schema(self.arrow_schema)
        files = self._old_files + self._new_files
        state = {
            "_data_files": [self._entries[f] for f in files],
            "_fingerprint": uuid.uuid4().hex[:16],
            "_format_columns": None,
            "_format_kwargs": {},
            "_format_type": None,
            "_output_all_columns": False,
            "_split": None,
        }
        info = {"citation": "", "description": f"illm {KIND} v{self.definition.version}",
                "features": features.to_dict(), "homepage": "", "license": ""}
        _fsync_write(self.workdir / INFO, json.dumps(info, indent=2))
        _fsync_write(self.workdir / STATE, json.dumps(state, indent=2))  # last: the commit point
        if self.workdir != self.out:
            self._swap_into_place()
        return self.out

    def _swap_into_place(self) -> None:
        old = None
        if self.out.exists():
            old = self.out.parent / f".{self.out.name}.old-{int(time.time())}-{uuid.uuid4().hex[:6]}"
            os.replace(self.out, old)
        os.replace(self.workdir, self.out)
        if old is not None:
            shutil.rmtree(old)

    def abort(self) -> None:
        """Drop what this writer staged; the dataset on disk stays as it was."""
        if self.workdir != self.out:
            shutil.rmtree(self.workdir, ignore_errors=True)
        else:
            for name in self._new_files:
                (self.out / name).unlink(missing_ok=True)

    def __enter__(self) -> "TrajectoryWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def open_table(path: str | Path, columns: list[str] | None = None) -> pa.Table:
    """Read a trajectory dataset as one pyarrow Table, refusing another kind or version."""
    root = Path(path)
    if not _is_dataset(root):
        raise UsageError(f"no trajectory dataset at {root}: run `illm collect --out {root}` first")
    tables = []
    for entry in _shard_entries(root):
        table = _read_shard(root, entry)
        schema_check.check(table.schema, KIND, root / entry["filename"])
        tables.append(table.select(columns) if columns else table)
    if not tables:
        return schemas.load(KIND).arrow.empty_table()
    return pa.concat_tables(tables)


def _parts(entries: list[dict]) -> list[dict]:
    """The collections a dataset was written by, in order, each with its settings and rows."""
    parts: dict[str, dict] = {}
    for e in entries:
        part = e.get("illm_part") or {"settings": "not recorded (written before illm recorded them)"}
        key = json.dumps(part, sort_keys=True)
        parts.setdefault(key, {**part, "rows": 0, "shards": 0})
        parts[key]["rows"] += int(e.get("illm_rows", 0))
        parts[key]["shards"] += 1
    return list(parts.values())


def info(path: str | Path) -> dict:
    """Rows, episodes, env ids, schema version and size of a trajectory dataset. Also checks
    dataset_info.json, which illm does not need but `datasets.load_from_disk` does."""
    root = Path(path)
    if _is_dataset(root):
        try:
            json.loads((root / INFO).read_text())["features"]
        except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as e:
            raise DamagedFileError(f"{root / INFO} is missing or damaged ({type(e).__name__}); illm can still read "
                                   f"the data, `datasets.load_from_disk` cannot: {_recollect(root)}") from None
    table = open_table(root, columns=["episode_id", "env_id", "policy", "terminated", "truncated", "reward"])
    files = _shard_files(root)
    kind, version = KIND, None
    if files:
        _, version = schema_check.kind_and_version(_read_shard(root, _shard_entries(root)[0]).schema)
    ends = table.filter(table["terminated"]) if table.num_rows else table
    successes = int(pc.sum(pc.greater(ends["reward"], 0)).as_py() or 0) if ends.num_rows else 0
    return {
        "path": str(root),
        "kind": kind,
        "schema_version": version if version is not None else schemas.load(KIND).version,
        "rows": table.num_rows,
        "episodes": len(pc.unique(table["episode_id"])) if table.num_rows else 0,
        "finished_episodes": len(pc.unique(table.filter(pc.or_(table["terminated"], table["truncated"]))["episode_id"]))
        if table.num_rows else 0,
        "successful_episodes": successes,
        "env_ids": sorted(pc.unique(table["env_id"]).to_pylist()),
        "policies": sorted(pc.unique(table["policy"]).to_pylist()),
        "shards": len(files),
        "parts": _parts(_shard_entries(root)),
        "bytes": sum((root / f).stat().st_size for f in files),
    }


def require_text(table: pa.Table, where: str | Path) -> None:
    """Refuse, in one line, a dataset whose rows have no observation text (a suite without a text
    renderer, e.g. Atari: renderer "none"): the language stages need text."""
    if not table.num_rows:
        return
    textless = pc.or_(pc.equal(table["renderer"], "none"), pc.is_null(table["obs_text"]))
    if pc.any(textless).as_py():
        envs = sorted(pc.unique(table.filter(textless)["env_id"]).to_pylist())
        raise UsageError(f"{where} holds steps of {', '.join(envs)}, which have no text observation: annotate "
                         "them with --mode hop (iLLM(hop): the observations translated into the LLM's embedding "
                         "space), or train them with --method ppo, rnd, ngu or apt")
