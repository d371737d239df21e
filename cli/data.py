"""`illm data`: inspect trajectory datasets."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.common import emit_json
from cli.errors import friendly

app = typer.Typer(help="Inspect trajectory datasets.", no_args_is_help=True)


@app.command("info", epilog="Example: illm data info data/traj/gotolocal --json")
@friendly
def info(
    path: Path = typer.Argument(..., help="Folder of a trajectory dataset."),
    as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
) -> None:
    """Rows, episodes, env ids and schema version of a trajectory dataset."""
    from illm_tools.data.trajectories import info as dataset_info

    stats = dataset_info(path)
    if as_json:
        emit_json(stats)
        return
    typer.echo(f"{stats['path']}: {stats['kind']} dataset, schema v{stats['schema_version']}")
    typer.echo(f"  rows        {stats['rows']:,}")
    typer.echo(f"  episodes    {stats['episodes']:,} ({stats['successful_episodes']:,} successful)")
    typer.echo(f"  env ids     {', '.join(stats['env_ids'])}")
    typer.echo(f"  policies    {', '.join(stats['policies'])}")
    typer.echo(f"  shards      {stats['shards']} ({stats['bytes'] / 1e6:.1f} MB)")
