"""The first hour of a new user (issue 49): nothing overwritten without an option, a cache that cannot
help a run named, live counts that include the shutdown, every error in one line, suffixes that match
their format, `illm cache show`, and `illm eval`'s interval."""

from __future__ import annotations

from typer.testing import CliRunner

from cli.main import app
from test_report import fake_run


def invoke(*args: str):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_report_refuses_an_out_folder_holding_files_unless_overwrite(tmp_path):
    fake_run(tmp_path / "run", 0, [(100, 1.0, 1), (200, 1.0, 1)])
    out = tmp_path / "rep"
    out.mkdir()
    (out / "report.md").write_text("my own notes")
    refused = invoke("report", tmp_path / "run", "--every", "100", "--out", out)
    assert refused.exit_code == 1, refused.output
    assert len(refused.output.strip().splitlines()) == 1 and "already holds report.md" in refused.output
    assert "--overwrite" in refused.output
    assert (out / "report.md").read_text() == "my own notes"  # nothing written
    assert sorted(p.name for p in out.iterdir()) == ["report.md"]
    merged = invoke("report", tmp_path / "a", tmp_path / "b", "--merge", "--out", out)
    assert merged.exit_code == 1 and "already holds report.md" in merged.output, merged.output
    empty = tmp_path / "empty"
    empty.mkdir()  # an empty folder is written into: it holds nothing to lose
    assert invoke("report", tmp_path / "run", "--every", "100", "--out", empty).exit_code == 0
    again = invoke("report", tmp_path / "run", "--every", "100", "--out", out, "--overwrite")
    assert again.exit_code == 0, again.output
    assert (out / "report.md").read_text() != "my own notes" and (out / "results.json").is_file()
