"""Where a result came from: the code (git commit, uncommitted changes, version) and the command line.

A training run appends one entry to `run_dir/provenance.json` each time a process starts training it
(a resumed run has one per start, with the frame it started from); `illm report` copies every run's
entries into results.json beside the report's own and says in report.md when runs were trained by
another commit than the one writing the report ("the runs predate the current code").

Read from `git` when the package is a git checkout (an installed wheel has no commit: None); a
separate file rather than config.json, whose keys are the run's settings and are compared on resume.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import time
from functools import cache
from pathlib import Path

NAME = "provenance.json"


@cache
def code() -> dict:
    """This process's code: {"commit": sha or None, "dirty": tracked files changed or None, "version"}."""
    from illm_tools import __version__

    root = Path(__file__).resolve().parent.parent

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    dirty = None if commit is None else bool(git("status", "--porcelain", "--untracked-files=no"))
    return {"commit": commit, "dirty": dirty, "version": __version__}


def command() -> str:
    """The command line of this process as a user would type it (`illm ...` for the console script)."""
    argv = list(sys.argv)
    if argv and Path(argv[0]).name == "illm":
        argv[0] = "illm"
    return shlex.join(argv)


def stamp(**extra) -> dict:
    """One provenance entry: the code, the command, the time (UTC) and `extra` (e.g. the start frame)."""
    return {**code(), "command": command(), "at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **extra}


def read(folder: Path) -> list[dict]:
    """A run folder's entries, oldest first; [] for a run written before provenance was recorded or a
    damaged file (provenance informs a report, it never stops one)."""
    try:
        entries = json.loads((Path(folder) / NAME).read_text())
    except (OSError, ValueError):
        return []
    return [e for e in entries if isinstance(e, dict)] if isinstance(entries, list) else []


def append(folder: Path, **extra) -> None:
    """Add this process's entry to `folder`'s provenance.json (written atomically)."""
    from illm_tools import durable

    durable.write_text(Path(folder) / NAME, json.dumps([*read(folder), stamp(**extra)], indent=2) + "\n")


def predating(commits: list[str | None], current: str | None) -> list[str]:
    """The distinct known commits in `commits` other than `current` (none when `current` is unknown)."""
    if current is None:
        return []
    return sorted({c for c in commits if c and c != current})
