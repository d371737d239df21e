"""A report folder's results.json read back (`read_results`) for `illm report --merge` and `--redraw`,
and checked before anything is written: a part's results.json is a file another session (or
another person) wrote, and a report built from it copies the heatmaps it names and draws every row.

`check_results` holds it to the shape `build.py` writes: each field the figures and report.md read,
of its type (a number, a list of numbers as long as the row's frames, ...), and every file it names
a bare name inside the part's folder (`illm_tools.folders.bare_name`), never `../x` or an absolute
path. A file that fails is refused in one line naming the file and the field (`DamagedFileError`),
before anything is written. The commands it recorded (its own, its parts', its runs' provenance) are
redacted as they are read (`illm_tools.provenance.redact`): a report written before secrets were
redacted passes none on. Fields added by later versions are left alone; a field an older
version did not write (a row's `settings`, its heatmaps, diagnostics, episode length) may be absent.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from illm_tools import provenance
from illm_tools.errors import DamagedFileError, UsageError
from illm_tools.folders import bare_name

NAME = "results.json"
REWRITE = "write that report again from its runs (`illm report RUNS --out DIR`)"


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _number(v: Any) -> bool:
    return (_int(v) or isinstance(v, float)) and math.isfinite(v)


def _str(v: Any) -> bool:
    return isinstance(v, str)


def _dict(v: Any) -> bool:
    return isinstance(v, dict)


def _or_none(test: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda v: v is None or test(v)


def _list_of(test: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, list) and all(test(x) for x in v)


def _dict_of(test: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda v: isinstance(v, dict) and all(test(x) for x in v.values())


_maybe_number = _or_none(_number)
_numbers = _list_of(_maybe_number)  # a series: NaN is written as null
_entries = _list_of(_dict)

# field -> (test, what it must be); ROW's are required, ROW_OPTIONAL's may be absent
ROW = {"env_id": (_str, "a string"), "label": (_str, "a string"), "method": (_str, "a string"),
       "score_name": (_str, "a string"), "seeds": (_list_of(_int), "a list of whole numbers"),
       "runs": (_list_of(_str), "a list of strings"), "short_runs": (_dict_of(_int), "a mapping run -> frames"),
       "trained_frames": (_dict_of(_int), "a mapping run -> frames"),
       "frames": (_list_of(_int), "a list of whole numbers"), "mean": (_numbers, "a list of numbers"),
       "std": (_numbers, "a list of numbers"), "band_low": (_numbers, "a list of numbers"),
       "band_high": (_numbers, "a list of numbers"), "final": (_dict, "a mapping")}
ROW_OPTIONAL = {"settings": (_or_none(_dict), "a mapping"), "visitation": (_or_none(_dict), "a mapping or null"),
                "bonus_map": (_or_none(_dict), "a mapping or null"), "diagnostics": (_or_none(_dict), "a mapping or null"),
                "episode_length": (_or_none(_dict), "a mapping or null"), "coverage": (_maybe_number, "a number or null"),
                "provenance": (_or_none(_dict_of(_entries)), "a mapping run -> list of entries"),
                "achievements": (_or_none(_dict), "a mapping or null")}
SCORES = {"n": (_int, "a whole number"), "iqm": (_maybe_number, "a number or null"),
          "ci_low": (_maybe_number, "a number or null"), "ci_high": (_maybe_number, "a number or null"),
          "mean": (_maybe_number, "a number or null"), "std": (_maybe_number, "a number or null")}
FINAL = {**SCORES, "frames": (_or_none(_int), "a whole number or null"), "per_seed": (_entries, "a list of mappings"),
         "no_score": (_list_of(_str), "a list of strings")}
FINAL_OPTIONAL = {"split": (lambda v: isinstance(v, bool), "true or false"),
                  "seed_curves": (_entries, "a list of mappings"), "points": (_list_of(_int), "a list of whole numbers")}
LENGTH = {**SCORES, "first": (_maybe_number, "a number or null"), "last": (_maybe_number, "a number or null")}
LENGTH_OPTIONAL = {"time_limit": (_or_none(_int), "a whole number or null")}
SERIES = ("success", "adv_ratio", "head_agreement", "bonus_paid")  # `diagnostics.SERIES`, as written
DIAGNOSTICS = {"frames": (_list_of(_int), "a list of whole numbers"),
               **{name: (_numbers, "a list of numbers") for name in SERIES},
               "paid_solved": (_maybe_number, "a number or null"), "paid_unsolved": (_maybe_number, "a number or null")}
DIAGNOSTICS_OPTIONAL = {"per_seed": (_entries, "a list of mappings")}
ACHIEVEMENTS = {"mean": (_dict_of(_number), "a mapping achievement -> rate"), "per_seed": (_entries, "a list of mappings")}
HEATMAP = {"png": (_str, "a file name"), "runs": (_list_of(_str), "a list of strings")}
SETTINGS = {"every": (_int, "a whole number"), "final_points": (_int, "a whole number"),
            "bootstrap_reps": (_int, "a whole number"), "bootstrap_seed": (_int, "a whole number")}
SETTINGS_OPTIONAL = {"command": (_or_none(_str), "a string"), "code": (_or_none(_dict), "a mapping"),
                     "parts": (_entries, "a list of mappings")}


def _fields(obj: dict, required: dict, optional: dict, where: str, refuse: Callable[[str], None]) -> None:
    for key, (test, what) in [*required.items(), *optional.items()]:
        if key not in obj:
            if key in required:
                refuse(f"{where} has no {key!r}")
        elif not test(obj[key]):
            refuse(f"{where}.{key} must be {what}, got {json.dumps(obj[key])[:60]}")


def _as_long(obj: dict, keys: tuple[str, ...], n: int, where: str, refuse: Callable[[str], None]) -> None:
    for key in keys:
        if len(obj[key]) != n:
            refuse(f"{where}.{key} has {len(obj[key])} values for {n} frames")


def _row(row: Any, where: str, envs: list, path: Path, refuse: Callable[[str], None]) -> None:
    if not _dict(row):
        refuse(f"{where} must be a mapping")
    _fields(row, ROW, ROW_OPTIONAL, where, refuse)
    if row["env_id"] not in envs:
        refuse(f"{where}.env_id {row['env_id']!r} is not among the file's envs")
    _as_long(row, ("mean", "std", "band_low", "band_high"), len(row["frames"]), where, refuse)
    if any(run not in row["trained_frames"] for run in row["runs"]):
        refuse(f"{where}.trained_frames misses one of its runs")
    final = row["final"]
    _fields(final, FINAL, FINAL_OPTIONAL, f"{where}.final", refuse)
    for i, seed in enumerate(final["per_seed"]):
        _fields(seed, {"seed": (_int, "a whole number"), "score": (_maybe_number, "a number or null")}, {},
                f"{where}.final.per_seed[{i}]", refuse)
    for i, curve in enumerate(final.get("seed_curves") or []):
        _fields(curve, {"seed": (_int, "a whole number"), "points": (_numbers, "a list of numbers")}, {},
                f"{where}.final.seed_curves[{i}]", refuse)
        _as_long(curve, ("points",), len(row["frames"]), f"{where}.final.seed_curves[{i}]", refuse)
    if row.get("episode_length"):
        _fields(row["episode_length"], LENGTH, LENGTH_OPTIONAL, f"{where}.episode_length", refuse)
    if row.get("achievements"):
        _fields(row["achievements"], ACHIEVEMENTS, {}, f"{where}.achievements", refuse)
    if row.get("diagnostics"):
        d = row["diagnostics"]
        _fields(d, DIAGNOSTICS, DIAGNOSTICS_OPTIONAL, f"{where}.diagnostics", refuse)
        _as_long(d, SERIES, len(d["frames"]), f"{where}.diagnostics", refuse)
        for i, seed in enumerate(d.get("per_seed") or []):
            _fields(seed, {"seed": (_int, "a whole number"), **{s: (_numbers, "a list of numbers") for s in SERIES}},
                    {}, f"{where}.diagnostics.per_seed[{i}]", refuse)
            _as_long(seed, SERIES, len(d["frames"]), f"{where}.diagnostics.per_seed[{i}]", refuse)
    for name in ("visitation", "bonus_map"):
        if row.get(name):
            _fields(row[name], HEATMAP, {}, f"{where}.{name}", refuse)
            bare_name(row[name]["png"], f"{path}: {where}.{name}.png", REWRITE, DamagedFileError)


def check_results(results: Any, path: Path) -> dict:
    """`results` (results.json's content, read from `path`) if it has the shape `build.py` writes (the
    module docstring); else DamagedFileError, one line naming `path` and the field."""
    def refuse(problem: str) -> None:
        raise DamagedFileError(f"{path} is not a report's results.json as illm writes it ({problem}): {REWRITE}")

    if not _dict(results):
        refuse("not a mapping")
    _fields(results, {"settings": (_dict, "a mapping"), "envs": (_list_of(_str), "a list of strings"),
                      "rows": (_list_of(lambda _: True), "a list")},
            {"quality": (_or_none(_dict), "a mapping or null"), "aggregate": (_or_none(_dict), "a mapping or null")},
            "the file", refuse)
    _fields(results["settings"], SETTINGS, SETTINGS_OPTIONAL, "settings", refuse)
    for i, row in enumerate(results["rows"]):
        _row(row, f"rows[{i}]", results["envs"], path, refuse)
    if results.get("aggregate"):
        _fields(results["aggregate"], {"envs": (_list_of(_str), "a list of strings"), "rows": (_entries, "a list of mappings")},
                {}, "aggregate", refuse)
    if results.get("quality"):
        _quality(results["quality"], refuse)
    return results


def _quality(quality: dict, refuse: Callable[[str], None]) -> None:
    """The annotator-quality curve's points, lines and markers (`quality.quality`), as its figure reads them."""
    _fields(quality, {k: (_entries, "a list of mappings") for k in ("points", "lines", "markers")},
            {"references": (_or_none(_dict), "a mapping")}, "quality", refuse)
    named = {"env_id": (_str, "a string"), "label": (_str, "a string"), "final": (_dict, "a mapping")}
    agreement = {"agreement": (_number, "a number")}
    for kind, fields in (("points", {**named, **agreement, "method": (_str, "a string")}), ("lines", named),
                         ("markers", {"env_id": (_str, "a string"), "model": (_str, "a string"),
                                      "backend": (_str, "a string"), **agreement})):
        for i, entry in enumerate(quality[kind]):
            _fields(entry, fields, {}, f"quality.{kind}[{i}]", refuse)
            if "final" in fields:
                _fields(entry["final"], {k: SCORES[k] for k in ("iqm", "ci_low", "ci_high")}, {},
                        f"quality.{kind}[{i}].final", refuse)


def read_results(folder: Path, what: str) -> dict:
    """A report folder's results.json, checked (`check_results`) and its recorded commands redacted;
    missing, unreadable or malformed, one line (`what`: the option's need, "--redraw takes a report folder")."""
    path = Path(folder) / NAME
    try:
        results = json.loads(path.read_text())
    except FileNotFoundError:
        raise UsageError(f"no {NAME} in {folder}: {what} written by `illm report --out`") from None
    except (OSError, ValueError, RecursionError) as e:  # not JSON, not UTF-8, nested too deep, a folder
        raise DamagedFileError(f"{path} is damaged ({type(e).__name__}): {REWRITE}") from None
    return _redacted(check_results(results, path))


def _redacted(results: dict) -> dict:
    """`results` with every command it recorded redacted (`provenance.redact`)."""
    settings = results["settings"]
    for entry in [settings, *settings.get("parts", [])]:
        if "command" in entry:
            entry["command"] = provenance.redact(entry["command"])
    for row in results["rows"]:
        if row.get("provenance"):
            row["provenance"] = {run: provenance.redact_entries(e) for run, e in row["provenance"].items()}
    return results
