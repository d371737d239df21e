"""One table from error type to exit code; every error reaches the user as one line."""

from __future__ import annotations

import errno
import functools
import os
import sys
from collections.abc import Callable

from typer import _click as click  # Typer's own copy of click: the one whose errors its commands raise

from illm_tools.errors import IllmError

# error type -> (exit code, prefix). The message itself says what to do next.
EXIT_CODES: dict[type[BaseException], tuple[int, str]] = {
    IllmError: (1, "error"),
    click.exceptions.ClickException: (1, "error"),  # an option click could not parse (`--frames 1e5`), a missing one
    FileNotFoundError: (1, "error: file not found"),
    PermissionError: (1, "error: permission denied"),
    KeyboardInterrupt: (130, "interrupted"),
    OSError: (1, "error"),  # after its subclasses above: a full disk, an unreadable folder
}


def report(exc: BaseException) -> int:
    """Print one line for a known error and return its exit code; re-raise unknown ones."""
    for kind, (code, prefix) in EXIT_CODES.items():
        if isinstance(exc, kind):
            msg = str(exc).strip().splitlines()[0] if str(exc).strip() else kind.__name__
            if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
                msg += " (free some space and run again: what was written before is whole)"
            print(f"{prefix}: {msg}", file=sys.stderr)
            if os.environ.get("ILLM_TRACEBACK"):
                raise exc
            return code
    raise exc


def usage_line(exc: BaseException) -> BaseException:
    """click's usage error as one line: its message, then the command's --help (Typer draws it as a box)."""
    ctx = getattr(exc, "ctx", None)
    if isinstance(exc, click.exceptions.UsageError) and ctx is not None:
        message = str(exc.format_message()).strip().splitlines()[0] if str(exc.format_message()).strip() else ""
        exc = IllmError(f"{message} (`{ctx.command_path} --help` lists the options)")
    return exc


def friendly(fn: Callable) -> Callable:
    """Decorator for a command: known errors become one line and a non-zero exit code
    (set ILLM_TRACEBACK=1 for the traceback)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except BrokenPipeError:  # the reader went away (`illm envs --json | head`): stop quietly, as SIGPIPE would
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's flush at exit must not fail
            raise SystemExit(141) from None
        except tuple(EXIT_CODES) as exc:  # noqa: B030
            raise SystemExit(report(exc)) from None

    return wrapper
