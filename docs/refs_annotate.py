"""Writing the references (`docs/refs.py`) that one field alone can mean, so that a person writes only the rest.

`python docs/refs_annotate.py PAGE...` adds, outside rendered blocks and comments:
- after each estimate with its interval (`0.941 [0.374, 0.999]`), the one field of the files the page
  links that prints as it (of the files its paragraph or table row links, first; one field in several
  reports, a part and the merged one, names the merged report; a report's row before its copy in the
  quality curve);
- after each number of a list of 5 or 10 seeds' finals (`0.90, 0.47, 0.67, 0.06, 0.87`), the seed's score in
  the one report row whose seeds print as the whole list, in order.
It says how many numbers it referenced and how many it left (several fields hold them, or none). A single
number is never referenced by its value alone: a 2-decimal value matches dozens of unrelated fields (a
curve's window, another level's spread), so a unique match is no evidence that it is the field meant.
"""

from __future__ import annotations

import re
import sys
from functools import cache
from pathlib import Path

from illm_tools.report.markdown import num

sys.path.insert(0, str(Path(__file__).resolve().parent))  # this folder's scripts (docs/ is no package)
import refs  # noqa: E402

RESULTS, ESTIMATE, load, units = refs.RESULTS, refs.ESTIMATE, refs.load, refs.units
shown_as, printed, BadRef, _printed, _is_number = refs.shown_as, refs.printed, refs.BadRef, refs._printed, refs._is_number
_estimates, resolve = refs._estimates, refs.resolve
IDENTIFIERS = ("env_id", "label", "method", "name", "model", "calibration", "env", "level", "seed", "key")
"""Fields that name a list's element, tried in this order when a path is written."""
SEEDS = re.compile(r"(?<![\d.\w\[-])\d\.\d{2}(?:, \d\.\d{2}){4}(?:(?:, \d\.\d{2}){5})?(?!\d|\.\d|<!--=|, \d)")
"""A list of 5 or 10 seeds' finals, as the pages print them."""


def _fields(node, path: str = "", series: bool = False):
    """(path, node, in a series) for every node of a JSON value; a list's objects are named by their
    identifying fields; a series is a list of more than 5 numbers (a curve's points)."""
    yield path, node, series
    if isinstance(node, dict):
        for key, value in node.items():
            step = f".{key}" if re.fullmatch(r"[A-Za-z_][\w-]*", str(key)) else f"[{key}]"
            yield from _fields(value, (path + step).lstrip("."))
    elif isinstance(node, list):
        curve = len(node) > 5 and all(map(_is_number, node))
        for i, value in enumerate(node):
            yield from _fields(value, f"{path}[{_selector(node, i)}]", curve)


def _selector(items: list, i: int) -> str:
    """The `key=value,...` of IDENTIFIERS that picks out items[i] alone (a report row's env and label, and as
    few more as it takes), else its index."""
    item = items[i]
    if not isinstance(item, dict):
        return str(i)
    keys = [k for k in IDENTIFIERS if k in item and isinstance(item[k], (str, int)) and not isinstance(item[k], bool)
            and '"' not in str(item[k])]
    base = [k for k in ("env_id", "label") if k in keys]  # a report's row by both, in a part as in the merged report
    rest = [k for k in keys if k not in base]
    for n in range(len(rest) + 1):
        for start in range(max(len(rest) - n + 1, 1)):
            chosen = base + rest[start:start + n]
            if not chosen:
                continue
            sel = {k: _printed(item[k]) for k in chosen}
            same = [e for e in items if isinstance(e, dict) and all(_printed(e.get(k)) == v for k, v in sel.items())]
            if len(same) == 1:
                return ",".join(f'{k}="{v}"' if set(v) & set(",=[]") else f"{k}={v}" for k, v in sel.items())
    return str(i)


@cache
def fields(file: str) -> tuple[tuple[str, object], ...]:
    """(path, number) of every number of docs/results/`file` but a series' points (no page quotes them
    singly)."""
    return tuple((path, node) for path, node, series in _fields(load(file)) if not series and _is_number(node))


@cache
def estimate_fields(file: str) -> tuple[tuple[str, str], ...]:
    """(path, as printed) of every estimate with its interval in docs/results/`file`, as `illm report`
    prints it."""
    out = []
    for path, node, _ in _fields(load(file)):
        for at in _estimates(path, node):
            value, low, high = refs.estimate(file, at)
            out.append((at, f"{num(value)} [{num(low)}, {num(high)}]"))
    return tuple(out)


def candidates(files: list[str], shown: str) -> list[tuple[str, str]]:
    """(file, path) of every field of `files` that prints as `shown`."""
    if re.fullmatch(ESTIMATE, shown):
        return [(file, path) for file in files for path, text in estimate_fields(file) if text == shown]
    return [(file, path) for file in files for path, node in fields(file) if printed(node, shown) == shown]


def linked_files(page: Path, text: str) -> list[str]:
    """The results files `page` links, as paths under docs/results."""
    found = set()
    for link in re.findall(r"\(([^()\s#]+)\)", text):
        target = (page.parent / link).resolve()
        if RESULTS in target.parents:
            if target.name == "report.md":
                target = target.with_name("results.json")
            if target.suffix == ".json" and target.is_file():
                found.add(str(target.relative_to(RESULTS)))
    return sorted(found)


def annotate(page: Path) -> tuple[int, int]:
    """Add a reference to each unreferenced estimate with its interval on `page`, outside its rendered
    blocks, that one field holds: of the files its paragraph (or table row) links, else of the files the
    page links; (numbers referenced, numbers left)."""
    text = page.read_text()
    files = linked_files(page, text)
    done = left = 0
    pattern = re.compile(rf"(?<![\d.\w\[-])({ESTIMATE})(?!<!--=)")
    pieces, last, start = [], 0, 0
    for unit in units(text):
        start = text.index(unit, start)
        near = linked_files(page, unit)
        for match in pattern.finditer(unit):
            at = start + match.end()
            if _inside_comment(text, start + match.start()) or _inside_block(text, start + match.start()):
                continue
            found = candidates(near, match.group(1)) if near else []
            if len(found) != 1:
                found = candidates(files, match.group(1))
            if len({path for _, path in found}) == 1:  # one field in several reports (a part and the merged one)
                found = sorted(found, key=lambda f: (len(f[0]), f[0]))[:1]
            rows = [f for f in found if f[1].startswith("rows[")]
            if len(found) > 1 and len(rows) == 1:  # a report's row, copied into its quality curve
                found = rows
            if len(found) == 1:
                pieces += [text[last:at], f"<!--= {found[0][0]} {found[0][1]} -->"]
                last, done = at, done + 1
            else:
                left += 1
        start += len(unit)
    page.write_text("".join(pieces) + text[last:])
    return done, left


def _inside_block(text: str, at: int) -> bool:
    """Whether `at` lies in a block docs/render.py writes (between `<!-- NAME:begin -->` and its end)."""
    begins = list(re.finditer(r"<!-- ([\w-]+):begin -->", text[:at]))
    return bool(begins) and f"<!-- {begins[-1].group(1)}:end -->" not in text[begins[-1].end():at]


def _inside_comment(text: str, at: int) -> bool:
    return text.rfind("<!--", 0, at) > text.rfind("-->", 0, at)


def seed_rows(files: list[str], shown: list[str]) -> list[tuple[str, str]]:
    """(file, row path) of every report row whose seeds' final scores print as `shown`, in seed order."""
    out = []
    for file in files:
        rows = load(file).get("rows") if isinstance(load(file), dict) else None
        for i, row in enumerate(rows or []):
            seeds = sorted((row.get("final") or {}).get("per_seed") or [], key=lambda s: s.get("seed", 0))
            if len(seeds) == len(shown) and all(_is_number(s.get("score")) and printed(s["score"], v) == v
                                                for s, v in zip(seeds, shown)):
                out.append((file, f"rows[{_selector(rows, i)}]"))
    return out


def annotate_seeds(page: Path) -> tuple[int, int]:
    """Reference each number of each seeds' list on `page` that one report row holds whole; (numbers
    referenced, lists left)."""
    text = page.read_text()
    files = linked_files(page, text)
    done = left = 0
    pieces, last = [], 0
    for match in SEEDS.finditer(text):
        if _inside_comment(text, match.start()) or _inside_block(text, match.start()):
            continue
        shown = match.group(0).split(", ")
        found = seed_rows(files, shown)
        if len({path for _, path in found}) == 1:
            found = sorted(found, key=lambda f: (len(f[0]), f[0]))[:1]
        if len(found) != 1:
            left += 1
            continue
        file, row = found[0]
        seeds = sorted(int(s["seed"]) for s in resolve(file, row)["final"]["per_seed"])
        pieces.append(text[last:match.start()])
        pieces.append(", ".join(f"{v}<!--= {file} {row}.final.per_seed[seed={s}].score -->" for s, v in zip(seeds, shown)))
        last, done = match.end(), done + len(shown)
    page.write_text("".join(pieces) + text[last:])
    return done, left


def main(argv: list[str]) -> int:
    for name in argv:
        page = Path(name).resolve()
        done, left = annotate(page)
        seeds, lists = annotate_seeds(page)
        print(f"{name}: {done} estimates and {seeds} seeds' finals referenced; {left} estimates and {lists} lists "
              "left (no field or several hold them)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
