"""Every result names the code and the command that produced it: a run's provenance.json (one entry
per start, resumes included), results.json's settings and rows, and report.md, which says when the
runs predate the code writing the report."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from typer.testing import CliRunner

from cli.main import app
from illm_tools import provenance

runner = CliRunner()
SMALL = ["--method", "ppo", "--num-envs", "2", "--num-steps", "32"]  # 64 frames per update
ROOT = Path(__file__).resolve().parent.parent


def illm(*args) -> str:
    out = runner.invoke(app, [*map(str, args)])
    assert out.exit_code == 0, out.output
    return out.output


def head() -> str | None:
    done = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    return done.stdout.strip() if done.returncode == 0 else None


def test_a_run_records_each_start_and_the_report_says_when_runs_predate_the_code(tmp_path, monkeypatch):
    run = tmp_path / "run"
    monkeypatch.setattr("sys.argv", ["/venv/bin/illm", "train", "--out", str(run)])
    illm("train", *SMALL, "--frames", 64, "--seed", 0, "--out", run)
    illm("train", "--out", run, "--resume", "--frames", 128)
    entries = json.loads((run / "provenance.json").read_text())
    assert [e["from_frame"] for e in entries] == [0, 64]
    assert entries[0]["commit"] == head() and entries[0]["version"] and entries[0]["command"].startswith("illm train")
    assert isinstance(entries[0]["dirty"], bool) or head() is None

    report = tmp_path / "report"
    illm("report", run, "--every", 64, "--out", report)
    results = json.loads((report / "results.json").read_text())
    assert results["settings"]["code"]["commit"] == head() and results["settings"]["command"].startswith("illm")
    (row,) = results["rows"]
    assert row["provenance"][str(run)] == entries
    text = (report / "report.md").read_text()
    if head() is None:  # an installed copy: no commit to compare
        return
    assert f"commit {head()[:12]}" in text and "predate" not in text

    older = [{**entries[0], "commit": "0" * 40}, entries[1]]  # the run was started by an older commit
    (run / "provenance.json").write_text(json.dumps(older))
    illm("report", run, "--every", 64, "--out", report, "--overwrite")
    text = (report / "report.md").read_text()
    assert "Runs predate the current code" in text and "000000000000 (1 run)" in text

    (run / "provenance.json").unlink()  # a run trained before provenance was recorded
    illm("report", run, "--every", 64, "--out", report, "--overwrite")
    assert "1 run recorded no provenance" in (report / "report.md").read_text()


def test_provenance_of_a_damaged_file_is_unknown_not_an_error(tmp_path):
    (tmp_path / "provenance.json").write_text("{not json")
    assert provenance.read(tmp_path) == []
    provenance.append(tmp_path, from_frame=3)
    (entry,) = provenance.read(tmp_path)
    assert entry["from_frame"] == 3 and "at" in entry
    assert provenance.predating(["a", None, "b", "a"], "b") == ["a"] and provenance.predating(["a"], None) == []
