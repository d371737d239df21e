"""README's results table is what docs/render.py renders from docs/results/*/results.json, digit for digit.

A number edited by hand in README.md's results block fails `test_readme_table_is_rendered`; the counts
"above" (IQM higher, as printed) and "clear of" (95% intervals apart) are checked against the rows they
count, and the splice refuses a README without its markers in one line."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _render():
    spec = importlib.util.spec_from_file_location("docs_render", ROOT / "docs" / "render.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


render = _render()


def test_readme_table_is_rendered():
    text = (ROOT / "README.md").read_text()
    assert render.splice(text, render.render()) == text, "run `python docs/render.py`"
    assert render.main(["--check"]) == 0


def test_a_hand_edited_number_fails(tmp_path, monkeypatch):
    text = (ROOT / "README.md").read_text()
    block = text.split(render.BEGIN, 1)[1].split(render.END, 1)[0]
    assert "0.508 [0.199, 0.785]" in block  # the report half's illm row, as the report prints it
    edited = tmp_path / "README.md"
    edited.write_text(text.replace("0.508 [0.199, 0.785]", "0.51 [0.20, 0.79]"))
    monkeypatch.setattr(render, "README", edited)
    assert render.main(["--check"]) == 1


def test_above_and_clear_are_two_counts():
    suite = render._load("suite-report")
    counts = render.counts(suite)
    finals = {(r["env_id"], r["label"]): r["final"] for r in suite["rows"]}
    assert set(counts["clear"]) <= set(counts["above"])
    for env in counts["clear"]:
        for control in render.CONTROLS:
            assert finals[(env, "illm")]["ci_low"] > finals[(env, control)]["ci_high"]
    # PutNextLocal: illm's IQM and the shuffled control's print the same, a tie, not "above"
    assert "BabyAI-PutNextLocal-v0" not in counts["above"]
    # GoToLocal is not in the suite; on the suite's levels bold marks exactly the clear ones
    rendered = render.render()
    assert rendered.count("**0.") + rendered.count("**1.") == len(counts["clear"])


def test_splice_without_markers_is_one_line():
    with pytest.raises(SystemExit, match="lacks the markers"):
        render.splice("no markers here", "block")
