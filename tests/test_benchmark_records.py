"""Every benchmark writes a record of what it measured (benchmarks/record.py), and docs/measured.md's
"Recorded benchmark outputs" table is rendered from the records (docs/render.py's `measured` block):
a figure edited in a record fails `python docs/render.py --check`, and a ratio that missed its target
is shown as missed."""

from __future__ import annotations

import datetime
import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if p.name != "record.py")


def _module(path: Path, name: str):
    """A script loaded from its file (neither benchmarks/ nor docs/ is a package)."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


records = _module(ROOT / "benchmarks" / "record.py", "benchmarks_record")
render = _module(ROOT / "docs" / "render.py", "docs_render_measured")


def _write(folder: Path, monkeypatch, **ratio) -> Path:
    monkeypatch.setattr(sys, "argv", ["benchmarks/keys.py", "--steps", "64", "--env", ""])
    return records.record("keys", {"rendered_us_per_state": 28.2, "state_keys_us_per_state": 9.84, "states": 64},
                          ratio={"name": "rendered / state_keys, time a state", **ratio}, out=folder,
                          settings={"steps": 64})


def test_record_writes_what_was_measured_and_where(tmp_path, monkeypatch, capsys):
    path = _write(tmp_path / "records", monkeypatch, value=2.87, target=3.0)
    assert re.fullmatch(r"keys-\d{8}-\d{6}\.json", path.name) and path.parent == tmp_path / "records"
    assert capsys.readouterr().out.strip() == f"record: {path}"
    entry = json.loads(path.read_text())
    assert set(entry) == {"benchmark", "command", "date", "code", "machine", "cores", "load_average_at_end",
                          "settings", "figures", "ratio"}
    assert entry["benchmark"] == "keys"
    assert entry["command"] == "python benchmarks/keys.py --steps 64 --env ''"  # an empty option kept
    assert datetime.datetime.fromisoformat(entry["date"]).strftime("%Y%m%d-%H%M%S") in path.name
    assert set(entry["code"]) >= {"commit", "dirty"}
    assert entry["machine"] and entry["cores"] == os.cpu_count() and len(entry["load_average_at_end"]) == 3
    assert entry["settings"] == {"steps": 64}
    assert entry["figures"] == {"rendered_us_per_state": 28.2, "state_keys_us_per_state": 9.84, "states": 64}
    assert entry["ratio"] == {"name": "rendered / state_keys, time a state", "value": 2.87, "target": 3.0,
                              "direction": "at_least", "met": False}
    again = _write(tmp_path / "records", monkeypatch, value=1.5, target=2.0, direction="at_most")
    assert len(list((tmp_path / "records").glob("keys-*.json"))) == 2  # one second apart or not, both kept
    assert json.loads(again.read_text())["ratio"]["met"] is True


def test_record_keeps_json_valid_and_refuses_a_bad_direction(tmp_path, monkeypatch):
    path = records.record("x", {"nan_s": float("nan")}, ratio={"name": "a / b", "value": float("inf")}, out=tmp_path)
    entry = json.loads(path.read_text())
    assert entry["figures"] == {"nan_s": None} and entry["ratio"]["value"] is None and entry["ratio"]["met"] is None
    with pytest.raises(ValueError, match="at_least, at_most"):
        records.record("x", {}, ratio={"name": "a / b", "value": 1.0, "direction": "above"}, out=tmp_path)
    with pytest.raises(TypeError, match="'label'"):
        records.record("x", {"label": "text"}, out=tmp_path)


def test_machine_is_lscpus_lines_or_the_cpus_name(monkeypatch):
    found = records.machine()
    if "Flags" in found:  # only the vector extensions are kept
        assert all(f.startswith(("avx", "amx", "fma")) for f in found["Flags"].split())
    assert set(found) <= {"Model name", "CPU family", "Model", "CPU(s)", "Thread(s) per core", "Flags", "cpu"}
    monkeypatch.setattr(records.shutil, "which", lambda _: None)
    assert records.machine() == {"cpu": records.cpu_name()}


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.stem)
def test_every_benchmark_takes_the_record_options_and_records(script):
    text = script.read_text()
    assert "options(parser)" in text, f"{script.name}: no --record/--no-record (record.options)"
    assert f'record("{script.stem}", ' in text, f"{script.name}: no record(...) call under its own name"
    assert "args.no_record" in text and "out=args.record" in text


def test_the_options_parse():
    import argparse

    parser = argparse.ArgumentParser()
    records.options(parser)
    assert parser.parse_args([]).record == records.RECORDS and not parser.parse_args([]).no_record
    assert parser.parse_args(["--record", "d", "--no-record"]).no_record


def test_a_benchmark_run_writes_its_record(tmp_path):
    """benchmarks/keys.py at a small size (about a second): its record beside its printed lines."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    command = [sys.executable, str(ROOT / "benchmarks" / "keys.py"), "--steps", "32"]
    done = subprocess.run([*command, "--record", str(tmp_path)], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "ratio" in done.stdout and "record: " in done.stdout
    (path,) = tmp_path.glob("keys-*.json")
    entry = json.loads(path.read_text())
    assert entry["benchmark"] == "keys" and entry["settings"]["steps"] == 32
    assert entry["ratio"]["target"] == 3.0 and entry["ratio"]["met"] == (entry["ratio"]["value"] >= 3.0)
    assert set(entry["figures"]) >= {"rendered_and_keyed_us_per_state", "state_keys_us_per_state"}
    done = subprocess.run([*command, "--record", str(tmp_path / "none"), "--no-record"], capture_output=True,
                          text=True, cwd=ROOT, env=env, timeout=120)
    assert done.returncode == 0 and "record: " not in done.stdout and not (tmp_path / "none").exists()


def test_the_pages_measured_block_is_rendered():
    assert render.blocks()["measured"][0] == render.MEASURED_PAGE
    text = render.MEASURED_PAGE.read_text()
    assert render.splice(text, render.render_measured(), "measured") == text, "run `python docs/render.py`"


def _page(tmp_path, monkeypatch) -> Path:
    """A copy of docs/measured.md reading the records in tmp_path/records, the only block checked."""
    monkeypatch.setattr(render, "RECORDS", tmp_path / "records")
    page = tmp_path / "measured.md"
    monkeypatch.setattr(render, "MEASURED_PAGE", page)
    monkeypatch.setattr(render, "blocks", lambda: {"measured": (page, render.render_measured)})
    (tmp_path / "records").mkdir(exist_ok=True)
    page.write_text(render.splice((ROOT / "docs" / "measured.md").read_text(), render.render_measured(), "measured"))
    return page


def test_no_record_yet(tmp_path, monkeypatch):
    page = _page(tmp_path, monkeypatch)
    assert "<!-- measured:begin -->\nno record yet\n<!-- measured:end -->" in page.read_text()


def test_a_figure_edited_in_a_record_fails_the_check(tmp_path, monkeypatch, capsys):
    path = _write(tmp_path / "records", monkeypatch, value=3.2, target=3.0)
    page = _page(tmp_path, monkeypatch)
    assert render.main(["--check"]) == 0
    assert "state_keys_us_per_state 9.84" in page.read_text() and "`python benchmarks/keys.py --steps 64" in page.read_text()
    entry = json.loads(path.read_text())
    entry["figures"]["state_keys_us_per_state"] = 8.5
    path.write_text(json.dumps(entry))
    capsys.readouterr()
    assert render.main(["--check"]) == 1
    assert "measured.md (measured)" in capsys.readouterr().out
    assert render.main([]) == 0 and "state_keys_us_per_state 8.50" in page.read_text()  # rendered again: fresh
    assert render.main(["--check"]) == 0


def test_a_missed_target_is_shown_missed(tmp_path, monkeypatch):
    _write(tmp_path / "records", monkeypatch, value=2.87, target=3.0)
    page = _page(tmp_path, monkeypatch).read_text()
    (row,) = [line for line in page.splitlines() if line.startswith("| [keys]")]
    assert "**2.87**" in row and "≥ 3" in row and "**missed**" in row and "**met**" not in row
    assert "AVX" in row or "cores" in row  # the machine in short
    cells = render.ratio_cells({"name": "a / b", "value": 59.1, "target": 2.0, "direction": "at_most", "met": False})
    assert cells == ["a / b: **59.1**", "≤ 2", "**missed**"]
    assert render.ratio_cells({"name": "a / b", "value": 0.5, "target": None, "direction": "at_least", "met": None})[2] == ""


def test_rows_are_newest_first(tmp_path, monkeypatch):
    folder = tmp_path / "records"
    folder.mkdir()
    for day in ("2026-11-27T10:00:00", "2026-11-28T09:00:00"):
        entry = json.loads(_write(tmp_path / "tmp", monkeypatch, value=3.5, target=3.0).read_text())
        (folder / f"keys-{day[:10]}.json").write_text(json.dumps({**entry, "date": day}))
    rows = [line for line in _page(tmp_path, monkeypatch).read_text().splitlines() if line.startswith("| [keys]")]
    assert [r.split(" | ")[1][:10] for r in rows] == ["2026-11-28", "2026-11-27"]
