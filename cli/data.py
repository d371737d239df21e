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
    typer.echo(f"  episodes    {stats['episodes']:,}: {stats['finished_episodes']:,} finished "
               f"({stats['successful_episodes']:,} successful), "
               f"{stats['episodes'] - stats['finished_episodes']:,} cut off by the end of collection")
    typer.echo(f"  env ids     {', '.join(stats['env_ids'])}")
    typer.echo(f"  policies    {', '.join(stats['policies'])}")
    typer.echo(f"  shards      {stats['shards']} ({stats['bytes'] / 1e6:.1f} MB)")
    for part in stats["parts"]:
        if "env_id" not in part:
            typer.echo(f"  part        {part['rows']:,} rows: settings {part['settings']}")
            continue
        dists = "" if part["num_dists"] is None else f", {part['num_dists']} distractors"
        options = "".join(f", {k}={v}" for k, v in (part.get("env_options") or {}).items())
        typer.echo(f"  part        {part['rows']:,} rows of {part['env_id']}: {part['action_space']} actions "
                   f"({part['actions']}){dists}{options}, episode seeds from {part['seed']:,}, "
                   f"policy {part['policy']}")


@app.command("coverage", epilog="Example: illm data coverage data/traj/gotolocal --cache data/ann --history 0 --history 3")
@friendly
def coverage(
    path: Path = typer.Argument(..., help="Folder of a trajectory dataset."),
    cache: Path = typer.Option(None, "--cache", help="Annotation cache to measure (leave out to see only the costs)."),
    history: list[int] = typer.Option([0, 1, 3], "--history", help="History lengths to measure (repeat the option)."),
    model: str = typer.Option(None, "--model", show_default=False,
                              help="LLM whose annotations count (as in `illm annotate`; default: the backend's)."),
    backend: str = typer.Option("transformers", "--backend", help="LLM backend (as in `illm annotate`)."),
    oracle_noise: float = typer.Option(0.0, "--oracle-noise", help="oracle: its noise (as in `illm annotate`)."),
    endpoint: str = typer.Option(None, "--endpoint", help="openai: the server's URL (as in `illm annotate`)."),
    embed_endpoint: str = typer.Option(None, "--embed-endpoint",
                                       help="openai: the pooling server's URL (as in `illm annotate`)."),
    tasks: str = typer.Option("action,summary", "--tasks", help="Tasks a state needs to count as covered."),
    layout: str = typer.Option("shared", "--layout", help="Prompt layout (as in `illm annotate`)."),
    dtype: str = typer.Option("auto", "--dtype", help="LLM compute dtype (as in `illm annotate`; auto: this machine's choice)."),
    quant: str = typer.Option("auto", "--quant", help="LLM quantisation (as in `illm annotate`; auto: the model's "
                              "alias on a GPU, else none)."),
    device: str = typer.Option("auto", "--device", help="Where `illm annotate` ran the LLM (auto: a GPU where "
                               "torch sees one): it decides what --quant auto and --dtype auto mean."),
    as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
) -> None:
    """What annotating a dataset would cost and reach, per history length.

    Per history length: distinct states, the share of steps the cache answers, the share the k
    most visited states cover (what annotating them with `illm annotate --limit k` reaches on this
    data), and a held-out estimate of what they reach on a run's new episodes (the top k of half
    the episodes against the other half's steps)."""
    from illm_tools.annotate.coverage import TOP_K, ahead_warning, measure_coverage
    from illm_tools.errors import UsageError
    from illm_tools.llm.spec import LLMSpec

    if not path.is_dir():
        raise UsageError(f"no trajectory dataset at {path}: pass a folder `illm collect` wrote")
    if cache is not None and not cache.is_dir():
        raise UsageError(f"no annotation cache at {cache}: check the path, or leave --cache out to see only the costs")

    llm = LLMSpec(backend=backend, model=model, dtype=dtype, quant=quant, device=device, oracle_noise=oracle_noise,
                  endpoint=endpoint, embed_endpoint=embed_endpoint)
    rows = measure_coverage(path, cache=cache, histories=history, llm=llm, layout=layout, tasks=tasks)
    if as_json:
        emit_json(rows)
        return
    typer.echo(f"{path}: {rows[0]['steps']:,} steps" + (f"; cache {cache}" if cache else "; no cache given"))
    head = "| history | distinct states | cached: states | cached: steps | " + " | ".join(
        f"top {k:,}: steps (new episodes)" for k in TOP_K) + " |"
    typer.echo(head)
    typer.echo("|" + "---|" * (4 + len(TOP_K)))
    for r in rows:
        held = r["heldout_top_k_step_share"]
        typer.echo(f"| {r['history']} | {r['distinct_states']:,} ({r['distinct_share']:.1%} of steps) | "
                   f"{r['cached_states']:,} | {r['cached_step_share']:.1%} | "
                   + " | ".join(f"{r['top_k_step_share'][str(k)]:.1%} ({held[str(k)]:.1%})" for k in TOP_K) + " |")
    typer.echo("top k: the share of these steps the k most visited states cover; in brackets, the share of "
               "every second episode's steps covered by the top k of the others: about what a training run, "
               "which plays new episodes, would find in a cache annotated from this data.")
    warning = ahead_warning(rows)
    if warning:
        typer.echo(warning, err=True)
