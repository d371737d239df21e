"""What a benchmark run measured, kept as one JSON file (`record`), so that docs/measured.md's table
of recorded outputs is rendered from files (`python docs/render.py`, its `measured` block) rather
than typed by hand.

A record holds the figures the run printed (name -> number, each name saying its unit), its headline
ratio against the baseline it measures in the same run (with the target the benchmark states, if
any, and whether the ratio met it: a miss is recorded, never dropped), the options that shaped the
figures, and what a figure cannot be read without: the command, the date, the code (git commit and
whether the tree was dirty), the machine (lscpu's lines: the CPU decides the kernels' speed), its
cores and its load average when the run ended (a busy machine's figures are not a quiet one's).

Every script in benchmarks/ takes `--record DIR` (default docs/results/measured/records/) and
`--no-record` (`options`), and calls `record` once at its end.
"""

from __future__ import annotations

import datetime
import json
import math
import numbers
import os
import platform
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "docs" / "results" / "measured" / "records"
"""Where a benchmark writes its record unless `--record DIR` says otherwise."""
LSCPU_LINES = ("Model name", "CPU family", "Model:", "CPU(s):", "Thread(s) per core", "Flags")
"""lscpu's lines a record keeps (each line whose text starts so)."""
VECTOR_FLAGS = ("avx", "amx", "fma")
"""The CPU flags kept: the vector extensions that decide the kernels' speed."""
DIRECTIONS = ("at_least", "at_most")


def cpu_name() -> str:
    """The CPU's model name from /proc/cpuinfo, else Python's word for the processor."""
    cpuinfo = Path("/proc/cpuinfo")
    for line in cpuinfo.read_text().splitlines() if cpuinfo.exists() else ():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def machine() -> dict:
    """lscpu's `LSCPU_LINES` (label -> text; the flags reduced to `VECTOR_FLAGS`), or {"cpu": the CPU's
    name} where lscpu is missing."""
    lscpu = shutil.which("lscpu")
    try:
        text = subprocess.run([lscpu], capture_output=True, text=True, timeout=30,
                              env={**os.environ, "LC_ALL": "C"}).stdout if lscpu else ""
    except (OSError, subprocess.SubprocessError):
        text = ""
    found = {line.split(":", 1)[0].strip(): line.split(":", 1)[1].strip() for line in text.splitlines()
             if line.startswith(LSCPU_LINES) and ":" in line}
    if "Flags" in found:
        found["Flags"] = " ".join(f for f in found["Flags"].split() if f.startswith(VECTOR_FLAGS))
    return found or {"cpu": cpu_name()}


def options(parser) -> None:
    """`--record DIR` and `--no-record` on a benchmark's argument parser."""
    parser.add_argument("--record", type=Path, default=RECORDS, metavar="DIR",
                        help="Write the run's record (figures, ratio, machine, command) into DIR "
                             "(default docs/results/measured/records).")
    parser.add_argument("--no-record", action="store_true", help="Write no record.")


def settings(args) -> dict:
    """A benchmark's options as a record keeps them (paths as text), less the record's own two."""
    return {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items() if k not in ("record", "no_record")}


def _number(name: str, value) -> float | int | None:
    """A figure as JSON holds it: an int or a float (numpy's scalars too), or None where there is none
    or it is not finite (NaN has no JSON form)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"figure {name!r} is {type(value).__name__}, not a number")
    if isinstance(value, numbers.Integral):
        return int(value)
    return float(value) if math.isfinite(value) else None


def headline(ratio: dict | None) -> dict | None:
    """The headline ratio as recorded: name, value, target, direction and met (None without a target
    or a value)."""
    if ratio is None:
        return None
    direction = ratio.get("direction", "at_least")
    if direction not in DIRECTIONS:
        raise ValueError(f"a ratio's direction is one of {', '.join(DIRECTIONS)}, not {direction!r}")
    value, target = _number("ratio", ratio.get("value")), ratio.get("target")
    value = None if value is None else float(value)
    target = None if target is None else float(target)
    met = None if value is None or target is None else (value >= target if direction == "at_least" else value <= target)
    return {"name": ratio["name"], "value": value, "target": target, "direction": direction, "met": met}


def record(benchmark: str, figures: dict, *, ratio: dict | None = None, out: Path | None = None,
           settings: dict | None = None) -> Path:
    """Write the run's record into `out` (default `RECORDS`, created) as BENCHMARK-YYYYMMDD-HHMMSS.json;
    prints "record: PATH" and returns the path. `ratio`: {"name": what is compared, "value", "target"
    (None: none stated), "direction": "at_least" (default) or "at_most"}; "met" is worked out here.
    The command is quoted as a shell would need it (an empty option stays '') and its secrets redacted
    (`illm_tools.provenance.redact_argv`)."""
    from illm_tools.provenance import code, redact_argv

    now = datetime.datetime.now()
    entry = {"benchmark": benchmark, "command": "python " + shlex.join(redact_argv(sys.argv)),
             "date": now.isoformat(timespec="seconds"), "code": code(), "machine": machine(),
             "cores": os.cpu_count(),
             "load_average_at_end": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
             "settings": settings or {}, "figures": {k: _number(k, v) for k, v in figures.items()},
             "ratio": headline(ratio)}
    folder = Path(RECORDS if out is None else out)
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"{benchmark}-{now:%Y%m%d-%H%M%S}"
    path, n = folder / f"{stem}.json", 2
    while path.exists():  # two runs in one second keep both records
        path, n = folder / f"{stem}-{n}.json", n + 1
    path.write_text(json.dumps(entry, indent=2, default=str) + "\n")  # an option of another type as text
    print(f"record: {path}")
    return path
