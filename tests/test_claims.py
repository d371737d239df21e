"""README's results table is what docs/render.py renders from docs/results/*/results.json, digit for digit.

A number edited by hand in README.md's results block fails `test_readme_table_is_rendered`; the counts
"above" (IQM higher, as printed) and "clear of" (95% intervals apart) are checked against the rows they
count, and the splice refuses a README without its markers in one line."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _docs_module(name: str):
    """docs/NAME.py loaded from its file (docs/ is no package)."""
    spec = importlib.util.spec_from_file_location(f"docs_{name}", ROOT / "docs" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


render, claims, refs = _docs_module("render"), _docs_module("claims"), _docs_module("refs")


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


def test_the_prior_probes_table_is_rendered_and_a_hand_edit_fails(tmp_path, monkeypatch):
    text = render.PROBE_PAGE.read_text()
    assert render.splice(text, render.render_probe(), "probe") == text, "run `python docs/render.py`"
    assert "| SmolLM2-135M | sum | 0.250 | 4.010 | 0.359 |" in text  # GoToLocal-smollm2-135m.json's sum row
    edited = tmp_path / "prior-probe.md"
    edited.write_text(text.replace("| 4.010 |", "| 3.989 |"))  # the stale table's value
    monkeypatch.setattr(render, "PROBE_PAGE", edited)
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


def test_every_result_on_the_result_pages_is_in_a_results_file_the_page_links():
    """README, docs/index.md and docs/experiments/*.md: each `0.901 [0.767, 0.953]` is held by a
    results.json the page links, or sits in a paragraph marked `<!-- computed: ... -->`."""
    found = [line for page in claims.pages() for line in claims.problems(page)]
    assert not found, "\n".join(found[:5])
    assert claims.main() == 0


@pytest.mark.parametrize("page, estimate", [
    ("README.md", "0.857 [0.765, 0.940]"),                   # the front page (its table also: rendered)
    ("docs/index.md", "0.974 [0.736, 0.994]"),               # the site's front page
    ("docs/experiments/paper-literal.md", "0.716 [0.619, 0.804]"),  # an experiment's page
])
def test_a_result_edited_by_hand_fails_on_each_kind_of_page(page, estimate):
    """Whether the estimate names its field (docs/refs.py holds it to that field) or not yet (the
    looser check of docs/claims.py), an edit fails one of the two checks."""
    path = ROOT / page
    text = path.read_text()
    assert estimate in text and not claims.problems(path, text) and not refs.check(path, text)
    value, rest = estimate.split(" ", 1)
    edited = text.replace(estimate, f"{float(value) + 0.01:.3f} {rest}", 1)
    (line,) = claims.problems(path, edited) + refs.check(path, edited)
    assert page in line


def test_the_loose_check_leaves_a_referenced_number_to_its_reference():
    path = ROOT / "docs" / "experiments" / "paper-literal.md"
    text = path.read_text()
    assert "0.716 [0.619, 0.804]<!--= " in text
    edited = text.replace("0.716 [0.619, 0.804]<!--= ", "0.726 [0.619, 0.804]<!--= ", 1)
    assert claims.problems(path, edited) == [] and len(refs.check(path, edited)) == 1


@pytest.mark.parametrize("page, single, edited", [
    ("docs/index.md", "SmolLM2 at 0.195", "SmolLM2 at 0.215"),  # a probe's agreement beside its report's link
    ("docs/experiments/paper-literal.md", "paper-literal 0.025 against", "paper-literal 0.215 against"),
])
def test_a_single_number_edited_by_hand_fails(page, single, edited):
    """A number with 2-3 decimals in a paragraph that links a results file is one that file holds (the
    page read without its references, as the loose check reads a number no reference names yet)."""
    path = ROOT / page
    text = refs.REF.sub(lambda m: m.group(1), path.read_text())
    assert single in text and not claims.problems(path, text)
    (line,) = claims.problems(path, text.replace(single, edited, 1))
    assert page in line and f"{claims.SINGLE.search(edited)[1]} is in none of the results files the page links" in line


def test_a_number_under_a_computed_marker_is_not_read(tmp_path):
    page = ROOT / "docs" / "experiments" / "distil.md"
    text = page.read_text()
    assert "0.782 on GoToLocal" in text and not claims.problems(page, text)
    unmarked = claims.COMPUTED.sub("", text)
    assert any("0.782 is in none" in line for line in claims.problems(page, unmarked))


def test_a_series_is_quoted_by_its_ends_only(tmp_path):
    """A list of more than SERIES numbers (a curve) offers only its first and last value to a page: its
    every point would match nearly any number a page could print (the number check's series rule)."""
    curve = [0.111, 0.222, 0.333, 0.444, 0.555, 0.666]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"curve": curve, "final": {"iqm": 0.777}, "short": [0.888, 0.999]}))
    held = claims.values(path)
    assert {"0.111", "0.666", "0.777", "0.888", "0.999"} <= held
    assert not {"0.222", "0.333", "0.444", "0.555"} & held


REF_PAGES = ["docs/index.md", "docs/experiments/suite.md", "docs/experiments/tables.md", "docs/measured.md",
             "docs/concepts/fidelity.md"]


def test_every_referenced_number_is_the_field_it_names():
    found = [line for page in refs.pages() for line in refs.check(page)]
    assert not found, "\n".join(found[:5])
    assert refs.main(["--check"]) == 0


def _one_digit_off(number: str) -> str:
    """`number` with its last digit changed by one (9 -> 8)."""
    i = max(i for i, c in enumerate(number) if c.isdigit())
    return number[:i] + str((int(number[i]) + 1) % 10 if number[i] != "9" else 8) + number[i + 1:]


@pytest.mark.parametrize("page", REF_PAGES)
def test_a_referenced_number_edited_by_one_digit_fails_on_each_kind_of_page(page):
    """Every kind of page: the site's front page, an experiment's, the measured figures, a concept's.
    Eight references spread over each page, each edited alone in its last digit."""
    path = ROOT / page
    text = path.read_text()
    matches = list(refs.REF.finditer(text))
    assert matches and not refs.check(path, text)
    for match in matches[::max(1, len(matches) // 8)][:8]:
        shown = match.group(1)
        head = shown.split(" [")[0]
        edited = text[:match.start()] + _one_digit_off(head) + shown[len(head):] + text[match.end(1):]
        (line,) = refs.check(path, edited)
        assert page in line and f"holds {shown}" in line


def test_a_reference_that_names_no_field_fails_in_one_line(tmp_path):
    page = ROOT / "docs" / "experiments" / "suite.md"
    text = "illm 0.901 [0.767, 0.953]<!--= suite-report/results.json aggregate.rows[label=illm-typo].iqm -->\n"
    (line,) = refs.check(page, text)
    assert "matches 0 elements, not one" in line
    assert refs.check(page, text.replace("suite-report/", "no-such-report/")) != []


@pytest.mark.parametrize("value, like, expected", [
    (0.9725, "98%", "97%"), (0.9725, "97.3%", "97.2%"), (204800, "1,000", "204,800"), (0.1345, "0.14", "0.13"),
    (0.1345, "0.134", "0.135"), (-0.0001, "0.00", "0.00"), (27.0, "27", "27"),
])
def test_a_number_prints_at_the_precision_the_page_gives_it(value, like, expected):
    assert refs.printed(value, like) == expected


def test_annotate_references_the_one_field_that_holds_an_estimate_or_a_seeds_list(tmp_path, monkeypatch):
    annotator = _docs_module("refs_annotate")
    results = tmp_path / "docs" / "results"
    (results / "r").mkdir(parents=True)
    seeds = [{"seed": s, "score": v} for s, v in enumerate((0.9, 0.25, 1.0, 0.5, 0.0))]
    rows = [{"env_id": "A", "label": "illm", "final": {"iqm": 0.5, "ci_low": 0.25, "ci_high": 0.75, "per_seed": seeds}},
            {"env_id": "B", "label": "illm", "final": {"iqm": 0.5, "ci_low": 0.25, "ci_high": 0.75}},
            {"env_id": "A", "label": "ppo", "final": {"iqm": 0.125, "ci_low": 0.0, "ci_high": 0.25}}]
    (results / "r" / "results.json").write_text(json.dumps({"rows": rows}))
    page = tmp_path / "docs" / "page.md"
    page.write_text("[report](results/r/report.md): ppo 0.125 [0.000, 0.250], illm 0.500 [0.250, 0.750], "
                    "its seeds 0.90, 0.25, 1.00, 0.50, 0.00.\n")
    monkeypatch.setattr(annotator.refs, "RESULTS", results)
    monkeypatch.setattr(annotator, "RESULTS", results)
    caches = (annotator.refs.load, annotator.fields, annotator.estimate_fields)
    for cached in caches:
        cached.cache_clear()
    try:
        assert annotator.annotate(page) == (1, 1)  # illm's estimate is held by two rows: left for a person
        assert annotator.annotate_seeds(page) == (5, 0)
        text = page.read_text()
        assert "0.125 [0.000, 0.250]<!--= r/results.json rows[env_id=A,label=ppo].final.iqm -->" in text
        assert "0.25<!--= r/results.json rows[env_id=A,label=illm].final.per_seed[seed=1].score -->" in text
        monkeypatch.setattr(refs, "RESULTS", results)
        refs.load.cache_clear()
        assert refs.check(page, text) == []
        assert len(refs.check(page, text.replace("0.25<!--=", "0.26<!--="))) == 1
    finally:
        for cached in (*caches, refs.load):
            cached.cache_clear()


@pytest.mark.parametrize("said, edited", [
    ("three<!--?# above: ", "two<!--?# above: "),    # the report half: illm above ppo on three of four
    ("it overlaps<!--? ", "it clear of<!--? "),       # the report half's aggregate overlaps ppo's
    ("interval is clear of<!--? suite-report/results.json ", "interval is overlaps<!--? suite-report/results.json "),
    ("illm is clear of<!--? ", "illm is overlaps<!--? "),  # LavaCrossingS9N1: illm's low end 0.406, rnd's high end 0.405
    ("every interval but rnd's overlaps<!--? suite-report/results.json ", "every interval overlaps<!--? "
     "suite-report/results.json rows[env_id=MiniGrid-LavaCrossingS9N1-v0,label=illm].final.iqm vs "
     "rows[env_id=MiniGrid-LavaCrossingS9N1-v0,label=rnd].final.iqm & "),  # the sentence as it stood
])
def test_a_verdict_word_that_contradicts_its_numbers_fails(said, edited):
    path = ROOT / "docs" / "experiments" / "suite.md"
    text = path.read_text()
    assert text.count(said) == 1 and not refs.check(path, text)
    (line,) = refs.check(path, text.replace(said, edited))
    assert "suite.md" in line


def test_verdict_words_follow_the_tie_rule():
    # PutNextLocal (suite-report): illm 0.011699 and the shuffled control's 0.011668 print 0.012 both
    illm, shuffled = (0.011699, 0.001, 0.023), (0.011668, 0.008, 0.018)
    assert refs.holds("tie", illm, shuffled) and not refs.holds("above", illm, shuffled)
    assert refs.holds("overlaps", illm, shuffled) and not refs.holds("clear of", illm, shuffled)
    assert refs.holds("clear of", (0.9, 0.8, 1.0), (0.1, 0.0, 0.2))
    assert refs.holds("below", (0.1, 0.0, 0.2), (0.9, 0.8, 1.0))
    with pytest.raises(refs.BadRef, match="no verdict word"):
        refs.holds("beats", illm, shuffled)


def test_the_audit_counts_an_edit_the_checks_catch_and_names_one_they_do_not(capsys):
    audit = _docs_module("audit")
    checks = (refs, claims, render)
    page = ROOT / "docs" / "experiments" / "suite.md"
    text = page.read_text()
    referenced = next(m for m in audit.numbers(text) if text.startswith("<!--= ", m.end()))
    assert audit.caught(page, audit.edited(text, referenced), checks)
    unlinked = "A sentence that links no results file says 0.37 here.\n"
    (m,) = audit.numbers(unlinked)
    assert not audit.caught(page, text + "\n" + audit.edited(unlinked, m), checks)
    assert audit.main(["5", "--seed", "1"]) in (0, 1)
    assert "of 5 one-digit edits caught" in capsys.readouterr().out


def test_the_audit_counts_only_what_the_checks_a_commit_meets_newly_report():
    """docs/measured.md is no page of the loose check (claims.py), whose complaints about it (the demo's Wilson
    intervals, which no results.json holds, where no marker pins them) once counted every edit there as caught."""
    audit = _docs_module("audit")
    checks = (refs, claims, render)
    page = ROOT / "docs" / "measured.md"
    text = page.read_text()
    unpinned_page = claims.COMPUTED.sub("", text)
    assert page not in claims.pages() and claims.problems(page, unpinned_page) != []
    assert audit.problems(page, unpinned_page, checks) == [] and audit.problems(page, text, checks) == []
    cosine = next(m for m in audit.numbers(text) if text.startswith("0.48 against 1.49 ms", m.start()))
    assert audit.caught(page, audit.edited(text, cosine), checks)          # pinned by its marker
    unpinned = text + "\nA figure no marker pins, 0.37 here.\n"
    (m,) = [m for m in audit.numbers(unpinned) if m.start() >= len(text)]
    assert not audit.caught(page, audit.edited(unpinned, m), checks)


def test_an_estimate_prints_at_the_precision_the_page_gives_it():
    """An episode length's estimate at one decimal, as the page prints it, is held to its field at that
    precision; a success rate's at three as before."""
    page = ROOT / "docs" / "experiments" / "paper-literal.md"
    row = 'suite-literal/results.json rows[env_id=BabyAI-UnlockLocal-v0,label="illm-setting=paper"]'
    text = f"77.6 [58.4, 95.0]<!--= {row}.episode_length.iqm --> and 0.974 [0.953, 0.994]<!--= {row}.final.iqm -->\n"
    assert refs.check(page, text) == []
    for edited in ("77.7 [58.4, 95.0]", "77.6 [58.4, 95.1]"):
        (line,) = refs.check(page, text.replace("77.6 [58.4, 95.0]", edited))
        assert "holds 77.6 [58.4, 95.0]" in line


def test_a_pinned_number_no_file_holds_fails_when_edited_alone():
    """A marker `<!-- computed: HOW, DATE; numbers: ... -->` lists the numbers before it in its paragraph or
    table row (back to the previous marker; a referenced number is its field's): an edit of one fails,
    and the audit counts it caught; a number after the last marker is not pinned."""
    audit = _docs_module("audit")
    page = ROOT / "docs" / "experiments" / "coverage.md"
    row = ("| ppo | 0.02 ± 0.03 | 88% | 0.716<!--= suite-literal/results.json aggregate.rows[label=illm-setting=paper].iqm"
           " --> |<!-- computed: illm report's output, not kept, 2026-11-22; numbers: 0.02 0.03 88% -->\n")
    text = f"| method | end | share | ref |\n|---|---|---|---|\n{row}\nAfter it 0.37 is not pinned.\n"
    assert refs.check(page, text) == []
    for match in audit.numbers(text):
        edited = audit.edited(text, match)
        if match.group(0) == "0.37":
            assert refs.check(page, edited) == []
            continue
        (line,) = refs.check(page, edited)
        assert "coverage.md" in line
        assert audit.caught(page, edited, (refs, claims, render))
    assert refs.check(page, text.replace("| 88% |", "| 88% | 0.5 |")) != []      # a number the marker misses
    (line,) = refs.check(page, text.replace(", 2026-11-22;", ";"))                # a marker with no date
    assert "names how and the date" in line
    quoted = text.replace("computed: illm report's output, not kept", "quoted: the paper's Table 1")  # a source's figures
    assert refs.check(page, quoted) == [] and len(refs.check(page, quoted.replace("| 88% |", "| 87% |"))) == 1


def test_a_number_before_a_full_stop_is_read_and_an_edit_of_it_fails():
    """`... near 1.2.`: the full stop ends the sentence, not the number; `1.2.3` (a version) is no result."""
    assert [m.group(0) for m in refs.numbers("RND keeps it near 1.2. Then 0.57.<!-- x --> and 0.3.\n")] == \
        ["1.2", "0.57", "0.3"]
    assert refs.numbers("vLLM 0.32.0, numba 0.68.1 and 127.0.0.1") == []
    audit = _docs_module("audit")
    page = ROOT / "docs" / "experiments" / "earlier.md"
    text = page.read_text()
    assert "illm 0.49 / 0.52 / 0.57.<!-- computed: " in text and not refs.check(page, text)
    (match,) = [m for m in audit.numbers(text) if text.startswith("0.57.<!-- computed: ", m.start())]
    (line,) = refs.check(page, audit.edited(text, match))
    assert "earlier.md" in line and "0.56" in line


def test_each_end_of_a_range_is_read_and_an_edit_of_either_fails():
    """`1.35-1.65`: two numbers, each pinned or referenced; a referenced range's upper end is not a negative number."""
    assert [m.group(0) for m in refs.numbers("entropy 1.35-1.65 of 1.79, cover 97-100%")] == ["1.35", "1.65", "1.79", "100%"]
    page = ROOT / "docs" / "experiments" / "suite.md"
    text = page.read_text()
    assert "stayed at 1.35-1.65 of 1.79<!-- computed: " in text and not refs.check(page, text)
    for edited in ("stayed at 1.34-1.65 of", "stayed at 1.35-1.66 of"):
        (line,) = refs.check(page, text.replace("stayed at 1.35-1.65 of", edited))
        assert "suite.md" in line
    distil = ROOT / "docs" / "experiments" / "distil.md"
    text = distil.read_text()
    found = re.search(r"the other four (0\.99)<!--= [^>]*-->-(1\.00)<!--= [^>]*-->", text)
    low, high = found.start(1), found.start(2)
    assert [m.group(1) for m in refs.REF.finditer(text) if low <= m.start() <= high] == ["0.99", "1.00"]
    for at, number in ((low, "0.98"), (high, "1.01")):
        (line,) = refs.check(distil, text[:at] + number + text[at + 4:])
        assert "distil.md" in line and number in line


def test_a_reference_to_several_fields_holds_the_number_each_prints():
    """`per_seed[seed!=4]` (every seed but 4) and `per_seed[*]`: the number is what every one of them prints."""
    page = ROOT / "docs" / "experiments" / "suite.md"
    text = page.read_text()
    said = "the other nine 1.00<!--= seeds-spread/results.json "
    assert said in text and not refs.check(page, text)
    (line,) = refs.check(page, text.replace(said, said.replace("1.00", "1.01")))
    assert "holds 1.00" in line
    row = "seeds-spread/results.json rows[env_id=MiniGrid-DoorKey-5x5-v0,label=illm].final.per_seed"
    (line,) = refs.check(page, f"all ten 1.00<!--= {row}[*].score -->\n")        # seed 4 ended at 0.08
    assert "print as 0.08, 1.00" in line
    (line,) = refs.check(page, f"its seed 1.00<!--= {row}[seed=9,seed!=9].score -->\n")
    assert "matches 0 elements" in line
