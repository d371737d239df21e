"""`illm report`: success-rate curves of training runs, grouped by method over seeds."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.common import emit_json
from cli.errors import friendly


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm report runs/gotolocal-* --every 20000")
    @friendly
    def report(
        runs: list[Path] = typer.Argument(..., help="Run folders written by `illm train`."),
        every: int = typer.Option(20_000, "--every", help="Frames per curve point (window of the success rate)."),
        as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
    ) -> None:
        """Success rate against frames, mean ± std over seeds, one row per method (a markdown table)."""
        from illm_tools.report.curves import summarise

        groups = summarise([r for r in runs if r.is_dir()], every)
        if as_json:
            emit_json([{"env_id": env, "method": method, **g} for (env, method), g in groups.items()])
            return
        frames = max((g["frames"] for g in groups.values()), key=len, default=[])
        typer.echo("| env | method | seeds | " + " | ".join(f"{f / 1000:.4g}k" for f in frames) + " | targets covered |")
        typer.echo("|---" * (4 + len(frames)) + "|")
        for (env, method), g in groups.items():
            cells = ["-" if m != m else f"{m:.2f} ± {s:.2f}" for m, s in zip(g["mean"], g["std"])]  # m != m: no episode
            cells += [""] * (len(frames) - len(cells))
            cover = f"{g['coverage']:.2f}" if method != "ppo" else "-"
            typer.echo(f"| {env} | {method} | {len(g['seeds'])} | " + " | ".join(cells) + f" | {cover} |")
