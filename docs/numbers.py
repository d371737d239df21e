"""Every result on the pages that report results is read from a file, never typed by hand.

The pages: README.md, docs/index.md and docs/experiments/*.md. A result there is an estimate with
its interval as `illm report` prints it, `0.901 [0.767, 0.953]` (an IQM, a mean or a probability of
improvement, with its 95% interval, 3 decimals). Each must be one that a results.json the page links
holds (a link to docs/results/NAME/report.md or results.json anywhere on the page makes NAME's
results a source of the page): its rows' finals, its aggregates, the probabilities of improvement,
rounded as the report rounds them (`illm_tools.report.markdown.num`). A number no file holds (one
combined by hand from two reports, one from a run whose report was not kept) is allowed only in a
paragraph that says so in a marker naming how it was made: `<!-- computed: COMMAND, DATE -->`.

`python docs/numbers.py` lists what no linked file holds and exits 1 if anything is listed;
tests/test_claims.py runs the same check, so a number edited by hand fails the test suite.
README's results table is rendered from the files besides (`docs/render.py`).
"""

from __future__ import annotations

import json
import re
import sys
from functools import cache
from pathlib import Path

from illm_tools.report.markdown import num

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
ESTIMATE = re.compile(r"(?<![\d.])(\d+\.\d{3}) \[(\d+\.\d{3}), (\d+\.\d{3})\]")
"""An estimate with its interval, as `illm report` prints them."""
SOURCE = re.compile(r"results/([\w.-]+)/(?:report\.md|results\.json)")
"""A link to a results folder's report or results.json."""
COMPUTED = re.compile(r"<!-- computed: [^>]*\d{4}-\d{2}-\d{2}[^>]*-->")
"""A paragraph's marker for numbers no file holds: how they were made, and when."""
KEYS = (("iqm", "ci_low", "ci_high"), ("poi", "poi_low", "poi_high"), ("mean", "ci_low", "ci_high"))


def pages() -> list[Path]:
    """The pages whose results are checked."""
    return [ROOT / "README.md", ROOT / "docs" / "index.md", *sorted((ROOT / "docs" / "experiments").glob("*.md"))]


@cache
def estimates(name: str) -> frozenset[tuple[str, str, str]]:
    """Every (estimate, low, high) a results folder's results.json holds, as printed."""
    found: set[tuple[str, str, str]] = set()

    def walk(node) -> None:
        if isinstance(node, dict):
            for keys in KEYS:
                if all(isinstance(node.get(k), (int, float)) and not isinstance(node.get(k), bool) for k in keys):
                    found.add(tuple(num(node[k]) for k in keys))
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(json.loads((RESULTS / name / "results.json").read_text()))
    return frozenset(found)


def problems(page: Path, text: str | None = None) -> list[str]:
    """The estimates on `page` (its text: `text`, default the file's) that no results.json it links
    holds, outside paragraphs marked `<!-- computed: ... -->`; one line each."""
    text = page.read_text() if text is None else text
    sources = sorted({n for n in SOURCE.findall(text) if (RESULTS / n / "results.json").is_file()})
    known = frozenset().union(*(estimates(n) for n in sources))
    out = []
    for paragraph in re.split(r"\n\s*\n", text):
        if COMPUTED.search(paragraph):
            continue
        for estimate in ESTIMATE.findall(paragraph):
            if estimate not in known:
                where = ", ".join(sources) or "no results folder: link the report the number comes from"
                out.append(f"{page.relative_to(ROOT)}: {estimate[0]} [{estimate[1]}, {estimate[2]}] is in none of "
                           f"the results the page links ({where})")
    return out


def main() -> int:
    found = [line for page in pages() for line in problems(page)]
    for line in found:
        print(line)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
