"""Where a result came from: the code (git commit, uncommitted changes, version) and the command line.

A training run appends one entry to `run_dir/provenance.json` each time a process starts training it
(a resumed run has one per start, with the frame it started from); `illm report` copies every run's
entries into results.json beside the report's own and says in report.md when runs were trained by
another commit than the one writing the report ("the runs predate the current code").

Read from `git` when the package is a git checkout (an installed wheel has no commit: None); a
separate file rather than config.json, whose keys are the run's settings and are compared on resume.

Secrets never reach a file (`redact`): the value of every secret option (`secret_option`: a flag whose
last word is token, key, secret or password, as `--token` and `--annotator-token`; `--api-key-env`
names a variable and stays) is written as `REDACTED`, in both `--opt VALUE` and `--opt=VALUE`, and so
is the password of a URL (`http://user:PASSWORD@host`). The command is redacted when it is recorded
and again whenever an entry is read back, so a file written before this rule never passes a
token on into a report.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import time
from functools import cache
from pathlib import Path

NAME = "provenance.json"
REDACTED = "REDACTED"
"""What a secret's value is written as."""
SECRET_WORDS = ("token", "key", "secret", "password", "passwd")
"""The last word of a secret option's flag (`--annotator-token`, `--api-key`)."""
_URL_PASSWORD = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.-]*://[^/@:\s?#]*):[^\s?#]*@(?=[^@/?#\s]*(?:[/?#]|$))")
"""A URL's user:password@ (the password may hold / and @: the host is what follows the last @ before
the path); the query and fragment are never read as credentials."""


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


def secret_option(flag: str) -> bool:
    """Whether the long option `flag` (`--annotator-token`) carries a secret: its last word is one of
    `SECRET_WORDS`. The one rule every record of a command line goes through (tests/test_trust_files.py
    holds every option of the command line to it)."""
    return flag.startswith("--") and flag[2:].lower().replace("_", "-").rsplit("-", 1)[-1] in SECRET_WORDS


def redact_argv(argv: list[str]) -> list[str]:
    """`argv` with every secret option's value (`--opt VALUE`, `--opt=VALUE`) and every URL's password
    replaced by `REDACTED`."""
    out, hide_next = [], False
    for arg in argv:
        if hide_next:
            out.append(REDACTED)
            hide_next = False
            continue
        flag, eq, _ = arg.partition("=")
        if secret_option(flag):
            out.append(f"{flag}={REDACTED}" if eq else arg)
            hide_next = not eq
            continue
        out.append(_URL_PASSWORD.sub(rf"\g<head>:{REDACTED}@", arg))
    return out


def redact(command: str | None) -> str | None:
    """A recorded command line with its secrets replaced (`redact_argv`); one that cannot be split as a
    shell would (unbalanced quotes) is withheld whole: what it hides cannot be told."""
    if command is None:
        return None
    try:
        return shlex.join(redact_argv(shlex.split(str(command))))
    except ValueError:
        return "(withheld: not a command line that can be checked for secrets)"


def redact_entries(entries: list) -> list[dict]:
    """Provenance entries (dicts) with their commands redacted; anything else in the list left out."""
    return [{**e, "command": redact(e.get("command"))} if "command" in e else e for e in entries if isinstance(e, dict)]


def command() -> str:
    """The command line of this process as a user would type it (`illm ...` for the console script),
    its secrets redacted (`redact_argv`)."""
    argv = list(sys.argv)
    if argv and Path(argv[0]).name == "illm":
        argv[0] = "illm"
    return shlex.join(redact_argv(argv))


def stamp(**extra) -> dict:
    """One provenance entry: the code, the command, the time (UTC) and `extra` (e.g. the start frame)."""
    return {**code(), "command": command(), "at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **extra}


def read(folder: Path) -> list[dict]:
    """A run folder's entries, oldest first, their commands redacted; [] for a run written before
    provenance was recorded or a damaged file (provenance informs a report, it never stops one)."""
    try:
        entries = json.loads((Path(folder) / NAME).read_text())
    except (OSError, ValueError):
        return []
    return redact_entries(entries) if isinstance(entries, list) else []


def append(folder: Path, **extra) -> None:
    """Add this process's entry to `folder`'s provenance.json (written atomically)."""
    from illm_tools import durable

    durable.write_text(Path(folder) / NAME, json.dumps([*read(folder), stamp(**extra)], indent=2) + "\n")


def predating(commits: list[str | None], current: str | None) -> list[str]:
    """The distinct known commits in `commits` other than `current` (none when `current` is unknown)."""
    if current is None:
        return []
    return sorted({c for c in commits if c and c != current})
