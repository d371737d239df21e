"""Option types and output helpers shared by the command modules."""

from __future__ import annotations

import json
import sys
from contextlib import contextmanager

import typer


def write_mode(append: bool, overwrite: bool) -> str:
    if append and overwrite:
        raise typer.BadParameter("--append and --overwrite exclude each other: pick one")
    return "append" if append else "overwrite" if overwrite else "new"


def emit_json(obj) -> None:
    typer.echo(json.dumps(obj, indent=2, sort_keys=True))


@contextmanager
def progress(total: int, description: str, unit: str = "steps"):
    """A rich progress bar on stderr; yields `advance(n, **fields)`."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    columns = [
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TextColumn("{task.fields[extra]}"),
        TimeElapsedColumn(),
    ]
    with Progress(*columns, console=console, transient=not sys.stderr.isatty(), disable=not console.is_terminal) as bar:
        task = bar.add_task(description, total=total or None, rate="", extra="")

        def advance(n: int, rate: float | None = None, total: int | None = None, **fields) -> None:
            """Move the bar by n; `total` sets the total once it is known."""
            extra = "  ".join(f"{k}={v}" for k, v in fields.items())
            if total is not None:
                bar.update(task, total=total)
            bar.update(task, advance=n, rate=f"{rate:,.2f} {unit}/s" if rate is not None else "", extra=extra)

        yield advance
