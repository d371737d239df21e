"""Annotation cache: round trip, de-duplication, crash safety, concurrent writers, damage
detection, merge, schema checks, and reading the shards without illm."""

from __future__ import annotations

import json
import os
import multiprocessing as mp
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from illm_tools.cache import AnnotationCache, merge, verify
from illm_tools.cache import layout
from illm_tools.cache.index import KeyIndex
from illm_tools.errors import CacheError, SchemaError
from fakes import keys_of, make_rows, run_writers

REPO = Path(__file__).resolve().parents[1]




def test_round_trip_lookup_and_columns(tmp_path):
    cache = AnnotationCache(tmp_path / "ann")
    rows = make_rows(0, 10)
    assert cache.write(rows).startswith("shard-")
    assert len(cache) == 10 and cache.tasks() == {"action": 5, "summary": 5}
    found = cache.lookup(keys_of(rows))
    assert [found[r["key"]] for r in rows] == rows
    assert set(cache.lookup(keys_of(rows), task="summary")) == set(keys_of(rows[1::2]))

    query = [rows[3]["key"], "0" * 64, rows[0]["key"], "not a key", rows[5]["key"]]
    assert cache.contains(query).tolist() == [True, False, True, False, True]
    cols = cache.get_columns(query, ["embedding", "cand_logprob_sum", "task"])
    assert cols["found"].tolist() == [True, False, True, False, True]
    emb = cols["embedding"]
    assert emb.dtype == np.float32 and emb.shape == (5, 4)
    assert emb[0].tolist() == [3.0, 0.5, -0.25, 1.0] and emb[4, 0] == 5.0
    assert np.isnan(emb[[1, 2, 3]]).all()  # absent, action row (null), absent
    assert cols["cand_logprob_sum"] == [None, None, [-0.75, -1.5], None, None]
    assert cols["task"] == ["summary", None, "action", None, "summary"]

    info = AnnotationCache(tmp_path / "ann").info()
    assert info["entries"] == 10 and info["shards"] == 1 and info["embedding_dims"] == [4]
    assert info["models"] == {"action/smollm2-135m": 5, "summary/smollm2-135m": 5}


def test_lookup_spans_many_shards_in_query_order(tmp_path):
    cache = AnnotationCache(tmp_path)
    for s in range(5):
        cache.write(make_rows(10 * s, 10 * s + 10))
    rows = make_rows(0, 50)
    order = np.random.default_rng(0).permutation(50)
    got = cache.get_columns([rows[i]["key"] for i in order], ["prompt"])["prompt"]
    assert got == [rows[i]["prompt"] for i in order]


@pytest.mark.parametrize("own_take", [1024, 10, 1])  # every shard small, some large (read from their values), all large
def test_matrices_are_the_columns_as_float_arrays_across_shards_nulls_and_misses(tmp_path, monkeypatch, own_take):
    """`get_matrices` (the trainer's look-up: read from each large shard's values, taken from the
    small ones together) holds what `get_columns` gives, as float32 [n, d] with NaN rows where a key
    is absent, its task is another or its value null; in the keys' order across shards of several
    sizes; a second width is refused."""
    from illm_tools.cache import store

    monkeypatch.setattr(store, "OWN_TAKE", own_take)
    cache = AnnotationCache(tmp_path)
    for lo, hi in ((0, 3), (3, 40), (40, 41), (41, 60)):
        cache.write(make_rows(lo, hi))
    rows = make_rows(0, 60)
    order = np.random.default_rng(1).permutation(60)
    query = [rows[i]["key"] for i in order] + ["0" * 64, "bad"]
    for task in (None, "action", "summary"):
        lists = cache.get_columns(query, ["embedding", "cand_logprob_sum", "cand_token_count"], task=task)
        mats = cache.get_matrices(query, ["embedding", "cand_logprob_sum", "cand_token_count"], task=task)
        assert mats["found"].tolist() == lists["found"].tolist()
        assert np.array_equal(mats["embedding"], lists["embedding"], equal_nan=True)
        for name in ("cand_logprob_sum", "cand_token_count"):
            m = mats[name]
            assert m.dtype == np.float32 and m.shape[0] == len(query)
            for got, want in zip(m, lists[name]):
                assert np.isnan(got).all() if want is None else got.tolist() == want
    assert mats["found"][:60].sum() == 30 and np.isnan(mats["cand_logprob_sum"]).all()  # summary: no scores
    wide = make_rows(60, 62)
    for row in wide:
        row["embedding"] = None if row["embedding"] is None else row["embedding"] * 2
        row["embedding_dim"] = None if row["embedding"] is None else len(row["embedding"])
    cache.write(wide)
    with pytest.raises(CacheError, match="embedding values of different sizes"):
        cache.get_matrices(keys_of(make_rows(0, 62)), ["embedding"])


def test_a_matrix_is_read_from_values_not_aligned_on_its_width():
    """A null entry that still spans values (Arrow allows it) leaves the rows after it off the
    width's grid: those are read value by value."""
    from illm_tools.cache.matrices import gather_matrix

    column = pa.ListArray.from_arrays(pa.array([0, 1, 3, 5], pa.int32()), pa.array([9.0, 1, 2, 3, 4], pa.float32()),
                                      mask=pa.array([True, False, False]))
    out = gather_matrix(lambda shard: column, [(0, np.array([2, 0, 1]), np.array([0, 2, 3]))], 4, "x")
    assert out[0].tolist() == [3.0, 4.0] and out[3].tolist() == [1.0, 2.0] and np.isnan(out[[1, 2]]).all()


def test_duplicate_keys_are_dropped(tmp_path):
    cache = AnnotationCache(tmp_path)
    rows = make_rows(0, 6)
    assert cache.write(rows + rows[:2]) is not None  # duplicates inside one batch
    assert len(cache) == 6 and verify(tmp_path).rows == 6
    assert cache.write(rows) is None  # nothing new: no shard
    name = cache.write(make_rows(4, 9))
    assert cache.shard_rows(name) == 3 and len(cache) == 9
    assert verify(tmp_path).ok and verify(tmp_path).shards == 2


def test_a_shard_is_visible_only_once_listed(tmp_path):
    cache = AnnotationCache(tmp_path)
    cache.write(make_rows(0, 3))
    table = pa.Table.from_pylist(make_rows(3, 6), schema=layout.arrow_schema())
    orphan = layout.write_shard(tmp_path, table)["name"]  # complete file, never listed
    fresh = AnnotationCache(tmp_path)
    assert len(fresh) == 3 and not fresh.contains(keys_of(make_rows(3, 6))).any()
    report = verify(tmp_path)
    assert report.ok and report.orphans == [orphan]
    assert fresh.adopt_orphans().adopted == [orphan]
    assert len(fresh) == 6 and verify(tmp_path).orphans == []

    partly_known = pa.Table.from_pylist(make_rows(4, 8), schema=layout.arrow_schema())
    orphan = layout.write_shard(tmp_path, partly_known)["name"]
    (tmp_path / "shard-truncated.arrow").write_bytes(layout.shard_bytes(partly_known)[:100])
    report = fresh.adopt_orphans()
    assert report.rewritten == [orphan] and report.rejected == ["shard-truncated.arrow"]
    assert len(fresh) == 8 and verify(tmp_path).ok and verify(tmp_path).rows == 8


def test_another_writers_shards_appear_after_refresh(tmp_path):
    reader, writer = AnnotationCache(tmp_path), AnnotationCache(tmp_path)
    writer.write(make_rows(0, 4))
    assert len(reader) == 0 and reader.refresh() == 1 and len(reader) == 4


def test_a_tail_reads_each_listed_shard_once_and_starts_over_on_a_rewritten_manifest(tmp_path):
    from illm_tools.cache.tail import ShardTail

    AnnotationCache(tmp_path).write(make_rows(0, 3))
    AnnotationCache(tmp_path).write(make_rows(3, 5))
    tail = ShardTail(tmp_path, ["key"])
    restarted, shards = tail.read()
    assert not restarted and [[r["key"] for r in rows] for rows in shards] == [keys_of(make_rows(0, 3)),
                                                                              keys_of(make_rows(3, 5))]
    assert tail.read() == (False, [])  # nothing new: nothing read again
    AnnotationCache(tmp_path).write(make_rows(5, 6))  # another writer: seen without any refresh
    assert tail.read() == (False, [[{"key": k} for k in keys_of(make_rows(5, 6))]])
    manifest = layout.read_manifest(tmp_path)
    manifest["shards"] = manifest["shards"][1:]  # rewritten (as a copy merged in place): the start differs
    layout.write_manifest(tmp_path, manifest)
    restarted, shards = tail.read()
    assert restarted and [len(rows) for rows in shards] == [2, 1] and len(tail.shards) == 2


CRASHING_WRITER = """
import os, sys
sys.path.insert(0, sys.argv[3])
from fakes import make_rows
from illm_tools.cache import AnnotationCache
def crash(self, stage):
    if stage == sys.argv[2]:
        os._exit(9)
AnnotationCache._checkpoint = crash
AnnotationCache(sys.argv[1]).write(make_rows(0, 10))
"""


@pytest.mark.parametrize("stage", ["shard-temp-written", "shard-renamed", "manifest-temp-written"])
def test_a_crash_leaves_a_valid_cache_and_a_rerun_writes_only_what_is_missing(tmp_path, stage):
    AnnotationCache(tmp_path).write(make_rows(0, 5))
    proc = subprocess.run(
        [sys.executable, "-c", CRASHING_WRITER, str(tmp_path), stage, str(Path(__file__).parent)],
        cwd=REPO, capture_output=True, text=True,
    )
    assert proc.returncode == 9, proc.stderr
    report = verify(tmp_path)
    assert report.ok and report.rows == 5
    assert len(report.orphans) == (0 if stage == "shard-temp-written" else 1)
    assert len(report.temp_files) == (0 if stage == "shard-renamed" else 1)

    cache = AnnotationCache(tmp_path)
    assert len(cache) == 5
    name = cache.write(make_rows(0, 10))  # the rerun
    assert cache.shard_rows(name) == 5 and len(cache) == 10
    repaired = cache.adopt_orphans()  # the crashed shard is now redundant
    assert repaired.removed == report.orphans and repaired.temp_removed == report.temp_files
    final = verify(tmp_path)
    assert final.ok and final.rows == 10 and not final.orphans and not final.temp_files


def test_a_crashed_shard_can_be_adopted_instead_of_rewritten(tmp_path):
    subprocess.run(
        [sys.executable, "-c", CRASHING_WRITER, str(tmp_path), "shard-renamed", str(Path(__file__).parent)],
        cwd=REPO, check=False,
    )
    cache = AnnotationCache(tmp_path)  # the very first write crashed: no manifest yet
    assert len(cache) == 0
    assert len(cache.adopt_orphans().adopted) == 1 and len(cache) == 10 and verify(tmp_path).ok


def _writer(root: str, worker: int, start: mp.Barrier) -> None:
    cache = AnnotationCache(root)
    start.wait()
    for s in range(20):
        cache.write(make_rows(0, 5, tag=f"w{worker}-s{s}"))



def test_two_processes_writing_concurrently_lose_nothing(tmp_path):
    assert run_writers(_writer, tmp_path, 2) == [0, 0]
    report = verify(tmp_path)
    assert report.ok and report.shards == 40 and report.rows == 200 and not report.orphans
    expected = [r["key"] for w in range(2) for s in range(20) for r in make_rows(0, 5, tag=f"w{w}-s{s}")]
    assert AnnotationCache(tmp_path).contains(expected).all()


def _flip_bytes(path: Path) -> None:
    """Damage a file in place, keeping its size. The mtime is moved on explicitly: a cache
    re-checks a file it already checked when (inode, size, mtime) change, and a write within
    the same clock tick as the original could keep the mtime."""
    st = path.stat()
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))


def test_a_damaged_shard_is_caught_by_verify_and_refused_by_lookup(tmp_path):
    cache = AnnotationCache(tmp_path)
    cache.write(make_rows(0, 5))
    name = cache.write(make_rows(5, 10))
    opened = AnnotationCache(tmp_path)
    _flip_bytes(tmp_path / name)
    report = verify(tmp_path)
    assert not report.ok and name in report.problems[0] and "sha256" in report.problems[0]
    with pytest.raises(CacheError, match=f"{name}.*illm cache verify"):
        AnnotationCache(tmp_path)
    with pytest.raises(CacheError, match=name):
        opened.lookup(keys_of(make_rows(5, 10)))  # already indexed: re-checked on read


def test_a_listed_shard_with_malformed_keys_is_refused(tmp_path):
    cache = AnnotationCache(tmp_path)
    layout.write_manifest(tmp_path, {**layout.empty_manifest(), "shards": [
        layout.write_shard(tmp_path, pa.Table.from_pylist(make_rows(0, 2), schema=layout.arrow_schema()))
    ]})
    bad = make_rows(2, 5)
    bad[1]["key"] = "Z" * 64
    entry = layout.write_shard(tmp_path, pa.Table.from_pylist(bad, schema=layout.arrow_schema()))
    manifest = layout.read_manifest(tmp_path)
    manifest["shards"].append(entry)
    layout.write_manifest(tmp_path, manifest)
    with pytest.raises(CacheError, match=f"shard {entry['name']}: row 1 "):
        cache.refresh()
    assert len(cache) == 0  # a refresh indexes all new shards or none
    assert entry["name"] in verify(tmp_path).problems[0]


def test_merge_of_overlapping_caches(tmp_path):
    a, b, into = tmp_path / "a", tmp_path / "b", tmp_path / "merged"
    AnnotationCache(a).write(make_rows(0, 10))
    AnnotationCache(b).write(make_rows(5, 12))
    AnnotationCache(b).write(make_rows(12, 15))
    before = {p.name: p.read_bytes() for src in (a, b) for p in src.iterdir()}
    report = merge([a, b], into)
    assert report.rows_copied == 15 and report.rows_skipped == 5 and len(report.shards_written) == 3
    assert {p.name: p.read_bytes() for src in (a, b) for p in src.iterdir()} == before
    check = verify(into)
    assert check.ok and check.keys == 15
    assert merge([b], into).rows_copied == 0  # idempotent
    assert merge([b], a).rows_copied == 5 and len(AnnotationCache(a)) == 15


def test_merge_refuses_damaged_sources_and_foreign_folders(tmp_path):
    a, into = tmp_path / "a", tmp_path / "into"
    name = AnnotationCache(a).write(make_rows(0, 4))
    _flip_bytes(a / name)
    with pytest.raises(CacheError, match="failed verification"):
        merge([a], into)
    assert not into.exists()
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(CacheError, match="not an annotation cache"):
        AnnotationCache(foreign)
    ok = tmp_path / "ok"
    AnnotationCache(ok).write(make_rows(0, 2))
    with pytest.raises(CacheError, match="not an annotation cache"):
        merge([ok], foreign)
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]


def test_shards_are_readable_by_plain_pyarrow_and_datasets(tmp_path):
    import datasets

    rows = make_rows(0, 6)
    name = AnnotationCache(tmp_path / "ann").write(rows)
    path = tmp_path / "ann" / name
    with pa.OSFile(str(path)) as f:
        table = pa.ipc.open_stream(f).read_all()
    assert table.to_pylist() == rows
    assert table.schema.metadata == {b"illm.kind": b"annotation", b"illm.version": b"1"}
    ds = datasets.Dataset.from_file(str(path))
    assert ds.num_rows == 6 and ds[1]["embedding"] == [1.0, 0.5, -0.25, 1.0]
    manifest = json.loads((tmp_path / "ann" / "manifest.json").read_text())
    assert [s["name"] for s in manifest["shards"]] == [name]


def test_schema_kind_and_version_mismatches_name_found_and_supported(tmp_path):
    cache = AnnotationCache(tmp_path / "v")
    name = cache.write(make_rows(0, 2))
    path = tmp_path / "v" / name
    table = layout.read_shard(path)
    future = table.replace_schema_metadata({b"illm.kind": b"annotation", b"illm.version": b"2"})
    path.write_bytes(layout.shard_bytes(future))
    manifest = json.loads((tmp_path / "v" / "manifest.json").read_text())
    manifest["shards"][0].update(sha256=layout.sha256_file(path), bytes=path.stat().st_size)
    (tmp_path / "v" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(SchemaError, match=r"'annotation' version '2'.*version\(s\) \[1\]"):
        AnnotationCache(tmp_path / "v")

    manifest.update(kind="trajectory", version=1)
    (tmp_path / "v" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(SchemaError, match=r"'trajectory' version 1.*'annotation' version\(s\) \[1\]"):
        AnnotationCache(tmp_path / "v")
    assert "trajectory" in verify(tmp_path / "v").problems[0]


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda r: r.pop("prompt"), r"missing columns \['prompt'\], unexpected columns \[\]"),
        (lambda r: r.update(extra=1), r"missing columns \[\], unexpected columns \['extra'\]"),
        (lambda r: r.update(goal=None), r"required columns \['goal'\]"),
        (lambda r: r.update(key="ABC"), "not a 64-character"),
        (lambda r: r.update(task=""), "every row needs a task name"),  # any name: tasks are plug-ins
        (lambda r: r.update(embedding_dim=3), "embedding_dim differs"),
        (lambda r: r.update(history_len="three"), "do not fit schema"),
    ],
)
def test_rows_that_do_not_match_the_schema_are_refused(tmp_path, change, message):
    rows = make_rows(0, 2)
    change(rows[1])
    with pytest.raises(CacheError, match=message):
        AnnotationCache(tmp_path).write(rows)
    assert not (tmp_path / "manifest.json").exists()


def test_index_survives_prefix_collisions():
    index = KeyIndex()
    a, b, c = "0" * 16 + "a" * 48, "0" * 16 + "b" * 48, "0" * 16 + "c" * 48
    assert index.add([a, b, a]).tolist() == [True, True, False]
    assert index.locate([b, a, c, "short"]).tolist() == [1, 0, -1, -1]
    assert index.add([c, b]).tolist() == [True, False] and len(index) == 3
