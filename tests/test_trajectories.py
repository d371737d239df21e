"""Trajectory datasets: the writer's modes, plain-library readability, and schema refusal."""

from __future__ import annotations

import json

import datasets
import pyarrow as pa
import pytest

import schemas
from illm_tools.data.trajectories import TrajectoryWriter, info, open_table
from illm_tools.errors import OutputExistsError, SchemaError, UsageError
from fakes import trajectory_rows as rows



def write(path, n=10, mode="new", shard_rows=4, episode=0):
    with TrajectoryWriter(path, mode=mode, shard_rows=shard_rows) as w:
        w.add(rows(n, episode))
    return w


def test_round_trip_with_plain_datasets_and_pyarrow(tmp_path):
    out = tmp_path / "traj"
    write(out, n=10, shard_rows=4)
    ds = datasets.load_from_disk(str(out))
    assert len(ds) == 10
    assert ds[3]["obs_text"] == "You see a wall 4 steps forward"
    assert ds.features["valid_actions"].feature.dtype == "string"
    table = open_table(out)
    assert table.num_rows == 10
    assert table.schema.metadata[schemas.KIND_KEY] == b"trajectory"
    state = json.loads((out / "state.json").read_text())
    assert len(state["_data_files"]) == 3  # 4 + 4 + 2 rows


def test_existing_output_is_refused_and_kept(tmp_path):
    out = tmp_path / "traj"
    write(out, n=5)
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(OutputExistsError, match="--append.*--overwrite"):
        TrajectoryWriter(out)
    assert sorted(p.name for p in out.iterdir()) == before
    assert open_table(out).num_rows == 5


def test_append_continues_episode_ids(tmp_path):
    out = tmp_path / "traj"
    write(out, n=5)
    w = TrajectoryWriter(out, mode="append")
    assert w.first_episode_id == 1
    with w:
        w.add(rows(3, episode=w.first_episode_id))
    stats = info(out)
    assert stats["rows"] == 8 and stats["episodes"] == 2 and stats["successful_episodes"] == 2


def test_overwrite_replaces_only_when_complete(tmp_path):
    out = tmp_path / "traj"
    write(out, n=5)
    with pytest.raises(RuntimeError):
        with TrajectoryWriter(out, mode="overwrite") as w:
            w.add(rows(3))
            raise RuntimeError("killed mid-way")
    assert open_table(out).num_rows == 5  # the old dataset survived the failed overwrite
    assert [p.name for p in tmp_path.iterdir()] == ["traj"]  # no staging folder left behind
    write(out, n=3, mode="overwrite")
    assert open_table(out).num_rows == 3


def test_overwrite_refuses_a_folder_that_is_not_a_dataset(tmp_path):
    out = tmp_path / "notes"
    out.mkdir()
    (out / "paper.txt").write_text("precious")
    with pytest.raises(OutputExistsError, match="not an illm trajectory dataset"):
        TrajectoryWriter(out, mode="overwrite")
    assert (out / "paper.txt").read_text() == "precious"


def _rewrite_metadata(out, metadata):
    """Rewrite the first shard with other schema metadata, as another writer would (its state.json
    entry updated too, so only the metadata differs)."""
    from illm_tools.cache.layout import sha256_file

    state = json.loads((out / "state.json").read_text())
    entry = state["_data_files"][0]
    shard = entry["filename"]
    table = pa.ipc.open_stream(pa.BufferReader((out / shard).read_bytes())).read_all()
    table = table.replace_schema_metadata(metadata)
    with pa.OSFile(str(out / shard), "wb") as sink, pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    entry.update(illm_bytes=(out / shard).stat().st_size, illm_sha256=sha256_file(out / shard))
    (out / "state.json").write_text(json.dumps(state))


def test_unknown_version_and_wrong_kind_are_refused(tmp_path):
    out = tmp_path / "traj"
    write(out, n=3, shard_rows=100)
    _rewrite_metadata(out, {b"illm.kind": b"trajectory", b"illm.version": b"99"})
    with pytest.raises(SchemaError, match="version 99.*supports trajectory schema version 1"):
        open_table(out)
    _rewrite_metadata(out, {b"illm.kind": b"annotation", b"illm.version": b"1"})
    with pytest.raises(SchemaError, match="holds a annotation dataset"):
        info(out)
    _rewrite_metadata(out, {})
    with pytest.raises(SchemaError, match="not an illm dataset"):
        open_table(out)


def test_missing_dataset_says_what_to_run(tmp_path):
    with pytest.raises(UsageError, match="illm collect"):
        open_table(tmp_path / "nothing")
