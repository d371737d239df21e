"""Every result on the pages that report results is read from a file, never typed by hand.

The pages: README.md, docs/index.md and docs/experiments/*.md. A result there is an estimate with
its interval as `illm report` prints it, `0.901 [0.767, 0.953]` (an IQM, a mean or a probability of
improvement, with its 95% interval, 3 decimals). Each must be one that a results.json the page links
holds (a link to docs/results/NAME/report.md or results.json anywhere on the page makes NAME's
results a source of the page): its rows' finals, its aggregates, the probabilities of improvement,
rounded as the report rounds them (`illm_tools.report.markdown.num`). A number no file holds (one
combined by hand from two reports, one from a run whose report was not kept) is allowed only in a
paragraph (or table row) that says so in a marker naming how it was made: `<!-- computed: COMMAND,
DATE -->` (or `<!-- quoted: SOURCE, DATE -->`, a source's figures; docs/refs.py's form of either, with
`; numbers: ...`, also pins them).

Single numbers too (`0.195`, `0.83`: two or three decimals, not a percentage): in a paragraph that
links a results file (a results folder's report or results.json, or any .json file under
docs/results), each must be a value some results file the page links holds, at the decimals the
page prints, or the paragraph carries the marker. (A number in a paragraph without such a link is
not read: "λ 0.8" is a setting, not a result.)

(The file is not named numbers.py: a script run from docs/ would shadow the standard library's `numbers`,
which numpy imports.) `python docs/claims.py` lists what no linked file holds and exits 1 if anything is listed;
tests/test_claims.py runs the same check, so a number edited by hand fails the test suite.
README's results table is rendered from the files besides (`docs/render.py`). This check is the loose one:
a number that names its field (`docs/refs.py`, `0.941 [0.374, 0.999]<!--= FILE PATH -->`) is held to that
one field, digit for digit, and this check only covers the numbers no reference names yet.
"""

from __future__ import annotations

import json
import re
import sys
from functools import cache
from pathlib import Path

from illm_tools.report.markdown import num


sys.path.insert(0, str(Path(__file__).resolve().parent))  # this folder's scripts (docs/ is no package)
import refs as _REFS  # noqa: E402

REFERENCED = _REFS.REF
"""A number that names its field: docs/refs.py holds it to that field; this check leaves it."""
units = _REFS.units

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
ESTIMATE = re.compile(r"(?<![\d.])(\d+\.\d{3}) \[(\d+\.\d{3}), (\d+\.\d{3})\]")
"""An estimate with its interval, as `illm report` prints them."""
SOURCE = re.compile(r"results/([\w.-]+)/(?:report\.md|results\.json)")
"""A link to a results folder's report or results.json."""
JSON_LINK = re.compile(r"\(([^()\s#]+\.json)\)")
"""A markdown link to a .json file (a probe's, a report's)."""
SINGLE = re.compile(r"(?<![\d.\[\w])(\d+\.\d{2,3})(?![\d\]%])")
"""A single number with two or three decimals, not a percentage and not part of an interval."""
COMPUTED = re.compile(r"<!-- (?:computed|quoted): [^>]*\d{4}-\d{2}-\d{2}[^>]*-->")
"""A paragraph's marker for numbers no file holds: how they were made (or what source they are quoted
from), and when."""
SERIES = 5
"""A list of more numbers than this is a series (a curve), whose points no page quotes singly."""
KEYS = (("iqm", "ci_low", "ci_high"), ("poi", "poi_low", "poi_high"), ("mean", "ci_low", "ci_high"))


def pages() -> list[Path]:
    """The pages whose results are checked."""
    return [ROOT / "README.md", ROOT / "docs" / "index.md", *sorted((ROOT / "docs" / "experiments").glob("*.md"))]


def _nodes(node):
    """Every node of a JSON value, depth first."""
    yield node
    for value in node.values() if isinstance(node, dict) else node if isinstance(node, list) else ():
        yield from _nodes(value)


@cache
def estimates(name: str) -> frozenset[tuple[str, str, str]]:
    """Every (estimate, low, high) a results folder's results.json holds, as printed."""
    return file_estimates(RESULTS / name / "results.json")


@cache
def file_estimates(path: Path) -> frozenset[tuple[str, str, str]]:
    """Every (estimate, low, high) a JSON file holds, as printed: a report's `KEYS` triples, and
    `illm act`'s success rate with its interval (`success_rate`, `success_interval` [low, high])."""
    found = set()
    for node in _nodes(json.loads(path.read_text())):
        if not isinstance(node, dict):
            continue
        found |= {tuple(num(node[k]) for k in keys) for keys in KEYS if all(_number(node.get(k)) for k in keys)}
        interval = node.get("success_interval")
        if _number(node.get("success_rate")) and isinstance(interval, list) and len(interval) == 2:
            found.add((num(node["success_rate"]), num(interval[0]), num(interval[1])))
    return frozenset(found)


def _number(node) -> bool:
    return isinstance(node, (int, float)) and not isinstance(node, bool)


@cache
def values(path: Path) -> frozenset[str]:
    """Every number a JSON file holds, printed with two and with three decimals; of a series (a list
    of more than `SERIES` numbers: a learning curve's, a diagnostic's windows) only its first and
    last, as reports quote them: its every point would match nearly any number a page could print."""
    def scalars(node):
        if isinstance(node, list) and len(node) > SERIES and all(map(_number, node)):
            yield from (node[0], node[-1])
            return
        if _number(node):
            yield node
        for value in node.values() if isinstance(node, dict) else node if isinstance(node, list) else ():
            yield from scalars(value)

    return frozenset(f"{x:.{d}f}" for x in scalars(json.loads(path.read_text())) for d in (2, 3))


def _json_files(page: Path, text: str) -> list[Path]:
    """The results files the page links: results folders' results.json, and .json files under docs/results."""
    linked = [(page.parent / link).resolve() for link in JSON_LINK.findall(text)]
    return sorted({p for p in linked if p.is_file() and RESULTS in p.parents} |
                  {RESULTS / n / "results.json" for n in SOURCE.findall(text) if (RESULTS / n / "results.json").is_file()})


def problems(page: Path, text: str | None = None) -> list[str]:
    """The estimates on `page` (its text: `text`, default the file's) that no results.json it links
    holds, and the single numbers of its paragraphs that link a results file that no file it links
    holds, outside paragraphs marked `<!-- computed: ... -->`; one line each."""
    text = REFERENCED.sub("", page.read_text() if text is None else text)
    sources = sorted({n for n in SOURCE.findall(text) if (RESULTS / n / "results.json").is_file()})
    files = _json_files(page, text)
    known = frozenset().union(*(estimates(n) for n in sources), *(file_estimates(f) for f in files))
    singles = frozenset().union(*(values(f) for f in files))
    where = ", ".join(str(f.relative_to(RESULTS)) for f in files) or "none: link the report the number comes from"
    out = []
    for paragraph in units(text):
        if COMPUTED.search(paragraph):
            continue
        for estimate in ESTIMATE.findall(paragraph):
            if estimate not in known:
                out.append(f"{page.relative_to(ROOT)}: {estimate[0]} [{estimate[1]}, {estimate[2]}] is in none of "
                           f"the results the page links ({where})")
        if JSON_LINK.search(paragraph) or SOURCE.search(paragraph):
            for single in SINGLE.findall(ESTIMATE.sub("", paragraph)):
                if single not in singles:
                    out.append(f"{page.relative_to(ROOT)}: {single} is in none of the results files the page links "
                               f"({where})")
    return out


def main() -> int:
    found = [line for page in pages() for line in problems(page)]
    for line in found:
        print(line)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
