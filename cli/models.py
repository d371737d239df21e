"""`illm models`: the model aliases and what each resolves to on this machine."""

from __future__ import annotations

import typer

from cli.common import emit_json
from cli.errors import friendly


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm models --json")
    @friendly
    def models(as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON.")) -> None:
        """List model aliases, what each resolves to, and whether it is available offline."""
        import dataclasses

        from illm_tools.llm.registry import list_models

        rows = list_models()
        if as_json:
            emit_json([dataclasses.asdict(r) for r in rows])
            return
        for r in rows:
            mark = "ok " if r.available else "-- "
            typer.echo(f"{mark}{r.alias:20s} {r.source:13s} {r.model_id}")
            typer.echo(f"     {r.where if r.available else 'unavailable: ' + r.where}")
            if r.notes:
                typer.echo(f"     {r.notes}")
