"""A number on a result page is a reference: it names the one field of a results file it shows.

The form, which reads as text in plain markdown and vanishes in the built site:

    0.941 [0.374, 0.999]<!--= seeds-candidate-report/results.json rows[env_id=MiniGrid-LavaCrossingS9N1-v0,label=illm].final -->
    0.1345 ... 0.13<!--= suite-report/results.json rows[env_id=X,label=illm].diagnostics.int_ext_ratio -->

FILE is a path under docs/results; PATH walks the JSON: `.key`, `[N]` (a list's Nth element, `[-1]` its last),
`[key=value,...]` (the one element of a list of objects whose fields print as the values; a value with
`,` `=` or `]` in quotes), `[KEY]`
(a key with characters a dotted step cannot hold); `[*]` (every element) and `[key!=value,...]` (every
element whose field does not print as the value) name several fields, and a number that names them is
what every one of them prints (`the other nine 1.00<!--= FILE rows[...].final.per_seed[seed!=4].score -->`).
The number before the comment is written from the field at the precision the page prints it: an object
with an estimate and its interval (`iqm`, `ci_low`, `ci_high`; `poi`...; `mean`...; `success_rate` with
`success_interval`) prints each of its three numbers at the decimals the page gives it, as `illm report`
prints it (`0.941 [0.374, 0.999]`) or otherwise (an episode length's `77.6 [58.4, 95.0]`); a number prints
with the decimals, the thousands separators and the percent sign the page gave it (`97%` is the field
0.9725 as a percentage).

A verdict word is checked the same way: `above<!--? FILE A vs B -->` (or *clear of*, *overlaps*, *below*,
*tie*: `holds`), A and B paths to estimates in FILE, is true by the tie rule or the check fails; a count,
`three<!--?# above: FILE A vs B; C vs D; ... -->`, is the number of comparisons it holds for.

A number no results file holds (a run whose output was not kept, a figure copied from a paper) is
pinned instead, by the marker that says how and when it was made listing the numbers it covers:
`<!-- computed: HOW, DATE; numbers: 0.02 0.03 88% -->` (`quoted: SOURCE, DATE; ...` for a source's
figures) covers the result numbers (`RESULT`: decimals and percentages, outside code, links and comments;
a referenced number is its field's) before it in its paragraph or table row, back to the previous such
marker, and each must be the one it lists in that place, so an edit of one of them alone fails. It pins
the page's text, not a source: the marker says where the numbers came from, and numbers traced to
nothing are only as good as that.

`python docs/refs.py` rewrites every referenced number from its field; `--check` lists each that differs
(and each reference that names no field) and exits 1, so a hand edit of a referenced number fails the test
suite (tests/test_claims.py). docs/refs_annotate.py writes the references one field alone can mean.

Written by hand: a number's format is the page's, and no templating
library keeps markdown readable as plain text while naming a JSON field beside each number.
"""

from __future__ import annotations

import json
import re
import sys
from functools import cache
from pathlib import Path

from illm_tools.report.markdown import beats, num

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
NUMBER = r"(?:(?<![\d>])-)?\d[\d,]*(?:\.\d+)?%?"
ESTIMATE = r"\d+\.\d+ \[\d+\.\d+, \d+\.\d+\]"
REF = re.compile(rf"({ESTIMATE}|{NUMBER})<!--= (\S+) (.+?) -->")
"""A referenced number: the number as printed, its file (under docs/results) and its path. A `-` is its
sign only where no digit or reference comes before it: in a range (`1.35-1.65`, `0.99<!--= ... -->-1.00`)
it is the dash between the ends."""
_START = r"(?:(?<![\w.\-/#=])|(?<=\d-)|(?<=-->-))"
"""Where a result number may start: not inside a word, a path, a version or a link; or as a range's upper end
(`1.35-1.65`: the `-` follows a digit, or the lower end's reference)."""
RESULT = re.compile(rf"{_START}\d[\d,]*\.\d+%?(?![\w/]|-(?!\d)|\.(?!\s|\Z|<))|{_START}\d+%(?![\w/]|-(?!\d))")
"""A result number as a page prints it: a decimal number or a percentage (`0.25`, `1,234.5`, `88%`). A full stop
after it followed by a space, a line's end or a comment (`... near 1.2.`) ends the sentence, not the number
(`1.2.3` is a version); each end of a range (`1.35-1.65`, `97-100%`) is a number of its own."""
HIDDEN = re.compile(r"```.*?```|`[^`\n]*`|<!--.*?-->|\]\([^)]*\)|!\[[^\]]*\]", re.S)
"""Code, HTML comments (a reference's own path), link targets and image alt texts: not results as read."""
PIN = re.compile(r"<!-- (computed|quoted): ([^>]*?); numbers: ([^>]*?) -->")
"""A marker that pins the numbers before it (see the module docstring): how and when, then the numbers;
`quoted:` where they are a source's (the paper's figures), not made here."""
STEP = re.compile(r'\.?([A-Za-z_][\w-]*)|\[((?:"[^"]*"|[^\]"])*)\]')
SELECT = re.compile(r'([\w-]+)(!?=)("[^"]*"|[^,"]*)(?:,|$)')
"""One `key=value` (or `key!=value`) of a selector; a value holding `,` `]` or `=` is quoted:
`[label="illm (a 1, b 2)"]`."""
TRIPLES = (("iqm", "ci_low", "ci_high"), ("poi", "poi_low", "poi_high"), ("mean", "ci_low", "ci_high"))


class BadRef(ValueError):
    """A reference that names no field."""


@cache
def load(file: str):
    path = RESULTS / file
    if not path.is_file():
        raise BadRef(f"{file} is not a file under docs/results")
    return json.loads(path.read_text())


def _printed(value) -> str:
    return num(value) if isinstance(value, float) else str(value)


def resolve(file: str, path: str):
    """The one field `path` names in docs/results/`file`."""
    nodes = resolve_all(file, path)
    if len(nodes) != 1:
        raise BadRef(f"{file} {path}: names {len(nodes)} fields, not one")
    return nodes[0]


def resolve_all(file: str, path: str) -> list:
    """The fields `path` names in docs/results/`file`: one, or several where it steps through `[*]` or a
    selector with `!=`."""
    nodes, pos = [load(file)], 0
    for step in STEP.finditer(path):
        if step.start() != pos:
            break
        pos = step.end()
        nodes = [found for node in nodes for found in _step(file, path, step, node)]
    if pos != len(path):
        raise BadRef(f"{file} {path}: cannot read the path from {path[pos:]!r}")
    return nodes


def _step(file: str, path: str, step: re.Match, node) -> list:
    """The nodes one step of `path` names in `node`."""
    key, selector = step.groups()
    if key is not None:
        if not isinstance(node, dict) or key not in node:
            raise BadRef(f"{file} {path}: no key {key!r} at {path[:step.start()] or 'the top'}")
        return [node[key]]
    if re.fullmatch(r"-?\d+", selector) and isinstance(node, list):
        if not -len(node) <= int(selector) < len(node):
            raise BadRef(f"{file} {path}: index {selector} out of range")
        return [node[int(selector)]]
    if selector == "*" and isinstance(node, list) and node:
        return list(node)
    if "=" in selector and isinstance(node, list):
        wanted = [(k, op == "=", v.strip('"')) for k, op, v in SELECT.findall(selector)]
        found = [e for e in node if isinstance(e, dict)
                 and all(k in e and (_printed(e[k]) == v) == same for k, same, v in wanted)]
        several = not all(same for _, same, _ in wanted)
        if not found or (len(found) != 1 and not several):
            raise BadRef(f"{file} {path}: [{selector}] matches {len(found)} elements, not one")
        return found
    if isinstance(node, dict) and selector in node:
        return [node[selector]]
    raise BadRef(f"{file} {path}: no element [{selector}]")


def estimate(file: str, path: str) -> tuple[float, float, float]:
    """The estimate and interval a path ending at an estimate's key names (`...final.iqm`, `...poi`,
    `...success_rate`): the key's value and its interval's ends, its siblings."""
    head, _, key = path.rpartition(".")
    parent = resolve(file, head) if head else load(file)
    if isinstance(parent, dict):
        for keys in TRIPLES:
            if keys[0] == key and all(_is_number(parent.get(k)) for k in keys):
                return tuple(parent[k] for k in keys)
        interval = parent.get("success_interval")
        if key == "success_rate" and _is_number(parent.get(key)) and isinstance(interval, list) and len(interval) == 2:
            return parent[key], interval[0], interval[1]
    raise BadRef(f"{file} {path}: not an estimate with its interval (end the path at iqm, poi, mean or success_rate)")


def _estimates(path: str, node):
    """The paths of the estimates an object holds (`PATH.iqm`, `PATH.poi`, ...)."""
    if isinstance(node, dict):
        held = [keys for keys in TRIPLES if all(_is_number(node.get(k)) for k in keys)]
        for keys in held:
            if keys[0] != "mean" or not any(k[0] == "iqm" for k in held):  # a report's mean is beside its IQM
                yield f"{path}.{keys[0]}".lstrip(".")
        interval = node.get("success_interval")
        if _is_number(node.get("success_rate")) and isinstance(interval, list) and len(interval) == 2:
            yield f"{path}.success_rate".lstrip(".")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def shown_as(file: str, path: str, like: str) -> str:
    """The field `path` names, printed in the format of `like` (the number as the page gives it)."""
    if re.fullmatch(ESTIMATE, like):
        (value, low, high), parts = estimate(file, path), re.findall(r"\d+\.\d+", like)
        return f"{printed(value, parts[0])} [{printed(low, parts[1])}, {printed(high, parts[2])}]"
    shown = {printed(node, like) for node in resolve_all(file, path)}
    if len(shown) != 1:
        raise BadRef(f"{file} {path}: its fields print as {', '.join(sorted(shown))}, not as one number")
    return shown.pop()


def printed(node, like: str) -> str:
    """A number printed in the format of `like`: its decimals, thousands separators and percent sign."""
    if not _is_number(node):
        raise BadRef(f"the field holds {type(node).__name__}, not a number")
    percent = like.endswith("%")
    body = like.rstrip("%")
    decimals = len(body.split(".")[1]) if "." in body else 0
    value = node * 100 if percent else node
    text = f"{value:,.{decimals}f}" if "," in body else f"{value:.{decimals}f}"
    if text.startswith("-") and float(text) == 0:
        text = text[1:]
    return text + ("%" if percent else "")


def rewrite(text: str) -> tuple[str, list[str]]:
    """`text` with each referenced number written from its field, and one line per reference that names no field."""
    errors = []

    def one(match: re.Match) -> str:
        shown, file, path = match.groups()
        try:
            return f"{shown_as(file, path, shown)}<!--= {file} {path} -->"
        except BadRef as exc:
            errors.append(f"{shown}<!--= {file} {path} -->: {exc}")
            return match.group(0)

    return REF.sub(one, text), errors


def pages() -> list[Path]:
    """Every page that may quote a result."""
    docs = ROOT / "docs"
    return [ROOT / "README.md", *sorted(p for p in docs.rglob("*.md") if RESULTS not in p.parents)]


def check(page: Path, text: str | None = None) -> list[str]:
    """One line for each referenced number of `page` that differs from its field or names none, for
    each verdict word its estimates contradict (`verdicts`) and for each pinning marker its numbers
    contradict (`pinned`)."""
    text = page.read_text() if text is None else text
    wanted, errors = rewrite(text)
    where = page.relative_to(ROOT) if ROOT in page.parents else page
    out = [f"{where}: {e}" for e in errors + verdicts(text) + pinned(text)]
    for have, want in zip(REF.finditer(text), REF.finditer(wanted)):
        if have.group(1) != want.group(1):
            out.append(f"{where}: {have.group(1)} where {have.group(2)} {have.group(3)} holds {want.group(1)}")
    return out


# Verdict words: "above", "clear of", "overlaps", "below" between two estimates, computed by the tie rule.

VERDICT = re.compile(r"(\w+(?: of)?)<!--\? (\S+) (.+?) -->")
"""A verdict word and the comparisons it states: `above<!--? FILE A vs B -->` (A and B paths to estimates;
`A vs B & A vs C`: every one of them)."""
COUNT = re.compile(r"(\w+)<!--\?# ([a-z ]+?): (\S+) (.+?) -->")
"""A count of the groups a verdict holds for: `three<!--?# above: FILE A vs B; C vs D; E vs F; G vs H -->` (a
group `A vs B & A vs C` counts where every comparison holds)."""
WORDS = ("zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")


def holds(word: str, mine: tuple, other: tuple) -> bool:
    """Whether `word` is true of estimate `mine` against `other` ((value, low, high) each) by the tie rule
    (`beats`: as printed, at 3 decimals): *above*/*below* compare the values, *clear of* the intervals
    (mine's low end above the other's high end), *overlap*, *overlaps*, *overlapping* neither interval clear of the
    other, *tie* the values equal as printed."""
    clear, under = beats(mine[1], other[2]), beats(other[1], mine[2])
    table = {"above": beats(mine[0], other[0]), "below": beats(other[0], mine[0]), "clear of": clear,
             "clear below": under, "overlaps": not clear and not under, "overlap": not clear and not under,
             "overlapping": not clear and not under,
             "tie": num(mine[0]) == num(other[0])}
    if word not in table:
        raise BadRef(f"{word!r} is no verdict word: one of {', '.join(table)}")
    return table[word]


def _pair(file: str, pair: str) -> tuple[tuple, tuple]:
    mine, sep, other = pair.partition(" vs ")
    if not sep:
        raise BadRef(f"{file} {pair}: a comparison is `A vs B`")
    return estimate(file, mine.strip()), estimate(file, other.strip())


def verdicts(text: str) -> list[str]:
    """One line per verdict word (or count of them) that its estimates contradict, or that names no field."""
    out = []
    def all_hold(word: str, file: str, group: str) -> bool:
        return all(holds(word, *_pair(file, pair)) for pair in group.split(" & "))

    for match in VERDICT.finditer(text):
        word, file, group = match.groups()
        try:
            if not all_hold(word, file, group):
                out.append(f"{word!r} is not what {file} {group} says")
        except BadRef as exc:
            out.append(f"{match.group(0)}: {exc}")
    for match in COUNT.finditer(text):
        said, word, file, groups = match.groups()
        try:
            n = sum(all_hold(word, file, group) for group in groups.split("; "))
        except BadRef as exc:
            out.append(f"{match.group(0)}: {exc}")
            continue
        if said not in (str(n), WORDS[n] if n < len(WORDS) else None):
            out.append(f"{said!r} where {word} holds for {n} of {len(groups.split('; '))} in {file}")
    return out


def numbers(text: str) -> list[re.Match]:
    """The result numbers of `text` (`RESULT`) outside code, links and comments (`HIDDEN`)."""
    hidden = [m.span() for m in HIDDEN.finditer(text)]
    return [m for m in RESULT.finditer(text) if not any(a <= m.start() < b for a, b in hidden)]


def pinned(text: str) -> list[str]:
    """One line per pinning marker (`PIN`) whose numbers are not the ones before it in its paragraph or
    table row, back to the previous marker (a referenced number left out: its field holds it)."""
    out = []
    for unit in units(text):
        last = 0
        for marker in PIN.finditer(unit):
            kind, how, listed = marker.groups()
            have = [m.group(0) for m in numbers(REF.sub("", unit[last:marker.start()]))]
            if not re.search(r"\d{4}-\d{2}-\d{2}", how):
                out.append(f"<!-- {kind}: {how}; ... -->: a pinning marker names how and the date")
            elif have != listed.split():
                out.append(f"the numbers {' '.join(have) or 'none'} where the marker `{how}` lists {listed}")
            last = marker.end()
    return out


def units(text: str) -> list[str]:
    """The page's paragraphs, a table's rows each on its own (a row's marker covers that row)."""
    out = []
    for paragraph in re.split(r"\n\s*\n", text):
        lines = paragraph.strip().splitlines()
        out += lines if lines and all(line.startswith("|") for line in lines) else [paragraph]
    return out


def main(argv: list[str]) -> int:
    found = []
    for page in pages():
        text = page.read_text()
        if "--check" in argv:
            found += check(page, text)
        else:
            wanted, errors = rewrite(text)
            found += [f"{page.relative_to(ROOT)}: {e}" for e in errors]
            if wanted != text:
                page.write_text(wanted)
    for line in found:
        print(line)
    if found and "--check" in argv:
        print("run `python docs/refs.py` to write each number from its field, or fix the reference")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
