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
from fakes import keys_of, make_rows, run_writers, stub_annotated

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
    stub_annotated(tmp_path / "src", 4)
    out = runner.invoke(app, ["cache", "export", str(tmp_path / "src"), "--out", str(tmp_path / "a.parquet")])
    assert out.exit_code == 0 and "exported 8 rows" in out.output
    out = runner.invoke(app, ["cache", "import", str(tmp_path / "a.parquet"), "--into", str(tmp_path / "dst")])
    assert out.exit_code == 0 and "8 new entries of its 8 rows (0 already present, 0 refused)" in out.output


def _tampered(rows: list[dict], how: str) -> None:
    """Damage the first row of its kind as a publisher of a shared dataset could."""
    action = next(r for r in rows if r["task"] == "action")
    summary = next(r for r in rows if r["task"] == "summary")
    if how == "re-keyed":  # the prompt edited under its old key
        action["prompt"] = action["prompt"].replace("red ball", "blue box")
    elif how == "nan":
        action["cand_token_logprobs"][0][0] = float("nan")
    elif how == "index":
        action["chosen_index"] = 99
    elif how == "not-best":
        action["chosen_index"] = min(range(len(action["cand_logprob_sum"])), key=action["cand_logprob_sum"].__getitem__)
    elif how == "lists":
        action["cand_token_count"] = action["cand_token_count"][:-1]
    elif how == "embedding":  # shorter than its dim says
        summary["embedding"] = summary["embedding"][:-1]
    elif how == "dim":  # consistent with itself, not with its model's other rows
        summary["embedding"], summary["embedding_dim"] = summary["embedding"][:-1], summary["embedding_dim"] - 1


@pytest.mark.parametrize("how,reason", [
    ("re-keyed", "its key is not the one its own columns give"), ("nan", "a log-prob is not a finite number"),
    ("index", "chosen_index is not its best candidate"), ("not-best", "chosen_index is not its best candidate"),
    ("lists", "its candidates' scores do not match its candidates"),
    ("embedding", "its embedding is not finite numbers of its stated dimension"),
    ("dim", "its embedding has 15 dimensions, its model's others 16")])
def test_a_bad_row_of_a_shared_file_is_kept_out_and_the_good_ones_enter(tmp_path, how, reason):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from illm_tools.cache import layout

    stub_annotated(tmp_path / "src", 6)
    export(tmp_path / "src", tmp_path / "ann.parquet")
    rows = pq.read_table(tmp_path / "ann.parquet").to_pylist()
    _tampered(rows, how)
    pq.write_table(pa.Table.from_pylist(rows, schema=layout.arrow_schema()), tmp_path / "bad.parquet")
    out = runner.invoke(app, ["cache", "import", str(tmp_path / "bad.parquet"), "--into", str(tmp_path / "dst")])
    assert out.exit_code == 0, out.output
    assert "11 new entries of its 12 rows (0 already present, 1 refused)" in out.output, out.output
    assert f"refused 1 rows (1 {reason}); first keys " in out.output, out.output
    assert len(AnnotationCache(tmp_path / "dst")) == 11 and verify(tmp_path / "dst").ok


def test_a_key_held_with_another_answer_keeps_the_caches_row_and_says_so(tmp_path):
    import pyarrow.parquet as pq

    stub_annotated(tmp_path / "dst", 2)
    stub_annotated(tmp_path / "src", 4)
    export(tmp_path / "src", tmp_path / "ann.parquet")
    table = pq.read_table(tmp_path / "ann.parquet")
    dst = AnnotationCache(tmp_path / "dst")
    held = dst.lookup(table.column("key").to_pylist())
    first = next(k for k in held if held[k]["task"] == "summary")
    rows = table.to_pylist()
    for r in rows:
        if r["key"] == first:  # the same inputs answered otherwise: the key is right, the text is not
            r["text"] = "go to the blue box, always"
    pq.write_table(table.from_pylist(rows, schema=table.schema), tmp_path / "other.parquet")
    out = runner.invoke(app, ["cache", "import", str(tmp_path / "other.parquet"), "--into", str(tmp_path / "dst")])
    assert out.exit_code == 0 and "kept the cache's own row for 1 keys it holds with another answer" in out.output
    assert AnnotationCache(tmp_path / "dst").lookup([first])[first]["text"] == held[first]["text"]


def test_a_copied_cache_whose_manifest_names_a_file_outside_it_is_refused_and_repair_moves_nothing_out(tmp_path):
    import json

    stub_annotated(tmp_path / "src", 2)
    outside = tmp_path / "outside.arrow"
    outside.write_bytes(b"not the cache's")
    manifest = json.loads((tmp_path / "src" / "manifest.json").read_text())
    manifest["shards"][0]["name"] = "../outside.arrow"
    (tmp_path / "src" / "manifest.json").write_text(json.dumps(manifest))
    out = runner.invoke(app, ["cache", "merge", str(tmp_path / "src"), "--into", str(tmp_path / "dst")])
    assert out.exit_code == 1 and "not a shard name of this cache" in out.output and not (tmp_path / "dst").exists()
    out = runner.invoke(app, ["cache", "repair", str(tmp_path / "src"), "--drop-damaged"])
    assert out.exit_code == 0, out.output
    assert outside.read_bytes() == b"not the cache's"  # never moved
    assert verify(tmp_path / "src").ok and len(AnnotationCache(tmp_path / "src")) == 4


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
