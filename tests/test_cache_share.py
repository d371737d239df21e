"""Sharing caches: export to Parquet and import back (keys never duplicated, damage refused, a
round trip through `datasets` keeps working), and three processes writing one cache at once with
overlapping keys, as trainers sharing a cache do: nothing lost, nothing stored twice."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.cache import AnnotationCache, verify
from illm_tools.cache.share import export, import_parquet
from illm_tools.errors import CacheError, OutputExistsError, SchemaError
from fakes import keys_of, make_rows, run_writers

runner = CliRunner()


def test_export_import_round_trip_skips_present_keys(tmp_path):
    src = AnnotationCache(tmp_path / "src")
    src.write(make_rows(0, 30))
    src.write(make_rows(30, 50))
    report = export(tmp_path / "src", tmp_path / "ann.parquet")
    assert report.rows == 50 and report.shards == 2
    with pytest.raises(OutputExistsError, match="--overwrite"):
        export(tmp_path / "src", tmp_path / "ann.parquet")
    dst = AnnotationCache(tmp_path / "dst")
    dst.write(make_rows(0, 10))
    report = import_parquet(tmp_path / "ann.parquet", tmp_path / "dst")
    assert report.rows == 50 and report.added == 40
    assert verify(tmp_path / "dst").rows == 50 and verify(tmp_path / "dst").ok
    again = import_parquet(tmp_path / "ann.parquet", tmp_path / "dst")
    assert again.added == 0 and verify(tmp_path / "dst").rows == 50
    got = AnnotationCache(tmp_path / "dst").lookup(keys_of(make_rows(0, 50)))
    want = AnnotationCache(tmp_path / "src").lookup(keys_of(make_rows(0, 50)))
    assert got.keys() == want.keys() and all(got[k]["text"] == want[k]["text"] for k in want)


def test_a_round_trip_through_datasets_imports_and_damage_is_refused(tmp_path):
    import datasets

    AnnotationCache(tmp_path / "src").write(make_rows(0, 12))
    export(tmp_path / "src", tmp_path / "ann.parquet")
    datasets.Dataset.from_parquet(str(tmp_path / "ann.parquet")).to_parquet(str(tmp_path / "hf.parquet"))
    assert import_parquet(tmp_path / "hf.parquet", tmp_path / "dst").added == 12
    table = pq.read_table(tmp_path / "ann.parquet").drop_columns(["text"])
    pq.write_table(table, tmp_path / "bad.parquet")
    with pytest.raises(SchemaError, match="does not hold annotation rows"):
        import_parquet(tmp_path / "bad.parquet", tmp_path / "dst2")
    (tmp_path / "junk.parquet").write_bytes(b"not parquet at all")
    with pytest.raises(CacheError, match="not a readable Parquet file"):
        import_parquet(tmp_path / "junk.parquet", tmp_path / "dst2")
    shard = next((tmp_path / "src").glob("*.arrow"))
    shard.write_bytes(shard.read_bytes()[:-10])
    out = runner.invoke(app, ["cache", "export", str(tmp_path / "src"), "--out", str(tmp_path / "x.parquet")])
    assert out.exit_code == 1 and "failed verification" in out.output and not (tmp_path / "x.parquet").exists()


def test_cli_export_and_import(tmp_path):
    AnnotationCache(tmp_path / "src").write(make_rows(0, 8))
    out = runner.invoke(app, ["cache", "export", str(tmp_path / "src"), "--out", str(tmp_path / "a.parquet")])
    assert out.exit_code == 0 and "exported 8 rows" in out.output
    out = runner.invoke(app, ["cache", "import", str(tmp_path / "a.parquet"), "--into", str(tmp_path / "dst")])
    assert out.exit_code == 0 and "8 new entries of its 8 rows" in out.output


def _trainer_like_writer(root: str, worker: int, start) -> None:
    cache = AnnotationCache(root)
    start.wait()
    for s in range(15):  # every worker answers the shared states 0..39 (in its own order) and a few of its own
        shared = make_rows((s * 7 + worker * 13) % 35, (s * 7 + worker * 13) % 35 + 5, tag="shared")
        cache.write(shared + make_rows(s, s + 1, tag=f"own{worker}"))


def test_three_processes_writing_overlapping_keys_lose_nothing_and_store_nothing_twice(tmp_path):
    assert run_writers(_trainer_like_writer, tmp_path, 3) == [0, 0, 0]
    report = verify(tmp_path)
    expected = set()
    for w in range(3):
        for s in range(15):
            start = (s * 7 + w * 13) % 35
            expected |= set(keys_of(make_rows(start, start + 5, tag="shared")))
            expected |= set(keys_of(make_rows(s, s + 1, tag=f"own{w}")))
    assert report.ok and not report.orphans and report.rows == len(expected)  # each key once
    assert AnnotationCache(tmp_path).contains(sorted(expected)).all()
