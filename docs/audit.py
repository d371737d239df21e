"""How many result numbers on the pages a hand edit could change unnoticed: the checks' own audit.

`python docs/audit.py [N] [--seed S]` draws N numbers (default 60) at random from the result pages
(README, docs/index.md, docs/experiments/*, docs/measured.md, docs/scale.md, docs/commands/serve.md): every
decimal number and percentage outside code, links and HTML comments. It edits each alone by one digit
(its last) and runs the checks a commit meets (`refs.check`: a number that names its field, and the verdict
words; `claims.problems`: the looser check, on the pages `claims.pages` names; `render`: the rendered
tables), then prints how many edits a check caught, and each one none caught with its page and line, so
that the next reference to write is named. An edit is caught when a check reports of the edited page
something it does not report of the page as it is (a page that fails already catches nothing by failing). A number no file holds counts as caught only where a marker pins it (`<!-- computed: HOW, DATE;
numbers: ... -->`, docs/refs.py), which refs.check holds to the numbers it lists. Exit 0 when at least
95% were caught (issue 72's bar), 1 otherwise.

Written by hand: it composes this folder's checks; no library audits markdown against JSON fields.
"""

from __future__ import annotations

import random
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "docs"))  # this folder's scripts (docs/ is no package)
import refs as _refs  # noqa: E402

NUMBER, SKIP = _refs.RESULT, _refs.HIDDEN
"""A result number, and what hides one (code, comments, link targets): docs/refs.py's, which its pinning
markers count by."""


def pages() -> list[Path]:
    docs = ROOT / "docs"
    return [ROOT / "README.md", docs / "index.md", *sorted((docs / "experiments").glob("*.md")), docs / "measured.md",
            docs / "scale.md", docs / "commands" / "serve.md"]


def numbers(text: str) -> list[re.Match]:
    """The result numbers of a page's text (see the module docstring)."""
    return _refs.numbers(text)


def edited(text: str, match: re.Match) -> str:
    """`text` with the number's last digit changed by one."""
    number = match.group(0)
    i = max(i for i, c in enumerate(number) if c.isdigit())
    digit = int(number[i])
    new = number[:i] + str(digit - 1 if digit else 1) + number[i + 1:]
    return text[:match.start()] + new + text[match.end():]


def caught(page: Path, text: str, checks) -> bool:
    """Whether the checks report of `text` (`page` edited) something they do not report of the page as it is."""
    return bool(set(problems(page, text, checks)) - set(problems(page, page.read_text(), checks)))


def problems(page: Path, text: str, checks) -> list[str]:
    """What the checks a commit meets report of `text` as `page`'s: the references, verdicts and pins
    (`refs.check`), the looser check on the pages it covers (`claims.pages`), the rendered blocks."""
    refs, claims, render = checks
    found = refs.check(page, text)
    if page.resolve() in {p.resolve() for p in claims.pages()}:
        found += claims.problems(page, text)
    for name, (where, make) in render.blocks().items():
        if where.resolve() == page.resolve() and render.splice(text, make(), name) != text:
            found.append(f"the {name} block differs from its rendering")
    return found


def main(argv: list[str]) -> int:
    n = int(argv[0]) if argv and argv[0].isdigit() else 60
    seed = int(argv[argv.index("--seed") + 1]) if "--seed" in argv else 0
    import claims
    import refs
    import render

    checks = (refs, claims, render)
    drawn = [(page, m) for page in pages() for m in numbers(page.read_text())]
    sample = random.Random(seed).sample(drawn, min(n, len(drawn)))
    missed = []
    for page, match in sample:
        text = page.read_text()
        if not caught(page, edited(text, match), checks):
            line = text.count("\n", 0, match.start()) + 1
            missed.append(f"  {page.relative_to(ROOT)}:{line}: {match.group(0)}")
    share = 1 - len(missed) / len(sample)
    print(f"{len(sample) - len(missed)} of {len(sample)} one-digit edits caught ({share:.0%}; {len(drawn):,} result "
          f"numbers on {len(pages())} pages, seed {seed}); not caught:")
    print("\n".join(missed) or "  none")
    return 0 if share >= 0.95 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
