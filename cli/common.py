"""Option types and output helpers shared by the command modules."""

from __future__ import annotations

import json
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import typer


def write_mode(append: bool, overwrite: bool) -> str:
    if append and overwrite:
        raise typer.BadParameter("--append and --overwrite exclude each other: pick one")
    return "append" if append else "overwrite" if overwrite else "new"


def emit_json(obj) -> None:
    typer.echo(json.dumps(obj, indent=2, sort_keys=True))


PLAIN_EVERY_S = 30.0
"""Without a terminal (a log file, a batch job), progress is one plain line this often."""


@contextmanager
def progress(total: int, description: str, unit: str = "steps"):
    """A rich progress bar on stderr (with the time left), or without a terminal a plain line on
    stderr every PLAIN_EVERY_S seconds; yields `advance(n, rate=None, total=None, **fields)`."""
    import time

    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    console = Console(stderr=True)
    columns = [
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TextColumn("{task.fields[extra]}"),
        TimeElapsedColumn(),
        TextColumn("left"),
        TimeRemainingColumn(),
    ]
    plain = not console.is_terminal
    state = {"done": 0, "total": total, "start": time.monotonic(), "said": time.monotonic()}
    with Progress(*columns, console=console, transient=not sys.stderr.isatty(), disable=plain) as bar:
        task = bar.add_task(description, total=total or None, rate="", extra="")

        def advance(n: int, rate: float | None = None, total: int | None = None, **fields) -> None:
            """Move the bar by n; `total` sets the total once it is known."""
            extra = "  ".join(f"{k}={v}" for k, v in fields.items())
            if total is not None:
                bar.update(task, total=total)
                state["total"] = total
            bar.update(task, advance=n, rate=f"{rate:,.2f} {unit}/s" if rate is not None else "", extra=extra)
            state["done"] += n
            now = time.monotonic()
            if plain and n and now - state["said"] >= PLAIN_EVERY_S:
                state["said"] = now
                speed = state["done"] / max(now - state["start"], 1e-9)
                left = (state["total"] - state["done"]) / speed if state["total"] and speed else None
                of = f"{state['total']:,}" if state["total"] else "?"
                print(f"{description}: {state['done']:,}/{of} {unit}"
                      + (f", {rate:,.2f} {unit}/s" if rate is not None else "")
                      + (f", about {_duration(left)} left" if left is not None else "")
                      + (f", {extra}" if extra else ""), file=sys.stderr, flush=True)

        yield advance


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else \
        f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


class Stop:
    """What `stop_on_signals` yields: `requested` turns true at the first SIGINT or SIGTERM, and
    `exit_code` is the shell's code for that signal (130 or 143)."""

    def __init__(self) -> None:
        self.signal: int | None = None

    @property
    def requested(self) -> bool:
        return self.signal is not None

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signal or 0)


@contextmanager
def stop_on_signals(what: str) -> Iterator[Stop]:
    """The first SIGINT or SIGTERM asks the work to stop at its next safe point (`what` it finishes,
    said in one line); a second one stops at once (KeyboardInterrupt, or exit 143 for SIGTERM:
    the files stay consistent because every write is atomic). Handlers are restored on exit."""
    stop = Stop()
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    def handler(signum, _frame) -> None:
        if stop.requested:
            for s, h in previous.items():
                signal.signal(s, h)
            if signum == signal.SIGTERM:
                raise SystemExit(128 + signum)
            raise KeyboardInterrupt
        stop.signal = signum
        print(f"{signal.Signals(signum).name}: finishing {what}; a second signal stops at once", file=sys.stderr)

    for s in previous:
        signal.signal(s, handler)
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def score_text(value: float | None) -> str:
    """A suite's score for people: "-" while no episode has ended (NaN), else 2 decimals."""
    return "-" if value is None or value != value else f"{value:.2f}"


def counted(n: int, word: str, plural: str | None = None) -> str:
    """ "1 shard", "2 shards", "1,024 runs": a count and its noun."""
    return f"{n:,} {word if n == 1 else plural or word + 's'}"


def save_figures(figures: dict, out, as_json: bool) -> bool:
    """A measuring command's figures written to `out` as JSON (whole or not at all; None: not written)
    and, with --json, printed; True when printed (the command prints nothing else)."""
    import json

    if out is not None:
        from illm_tools import durable

        out.parent.mkdir(parents=True, exist_ok=True)
        durable.write_text(out, json.dumps(figures, indent=2, sort_keys=True) + "\n")
    if as_json:
        emit_json(figures)
    return as_json
