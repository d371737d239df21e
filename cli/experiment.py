"""`illm experiment`: a grid of training runs from a YAML spec, N at a time, resumable."""

from __future__ import annotations

import inspect
from contextlib import nullcontext

import typer

from cli.common import Stop, counted, stop_on_signals
from cli.errors import friendly


EXAMPLE = ("Example: illm experiment experiments/specs/table1.yaml --jobs 2  (then: illm report results/table1 --out "
           "results/table1/report); on a SLURM cluster: illm experiment experiments/specs/table1.yaml --launcher slurm "
           "--partition gpu --gpus 1 --jobs 32")


def _parameters() -> list[inspect.Parameter]:
    from cli.options import dataclass_parameters
    from illm_tools.experiment import ExperimentConfig

    return dataclass_parameters(ExperimentConfig, arguments={"spec"})


def frames_text(spec) -> str:
    """"151,552 frames each", or with per-env frames "151,552 to 409,600 frames per run"."""
    counts = sorted({spec.env_frames.get(env, spec.frames) for env in spec.envs})
    if len(counts) == 1:
        return f"{counts[0]:,} frames each"
    return f"{counts[0]:,} to {counts[-1]:,} frames per run (env_frames)"


def register(app: typer.Typer) -> None:
    def experiment(**options) -> None:
        """Train every run of a spec's grid into one results folder; run again to resume.

        The grid is methods x envs x settings x seeds; finished runs are skipped, unfinished ones
        resumed."""
        from cli.options import config_from_options
        from illm_tools.experiment import ExperimentConfig, plan, run_experiment, select, unavailable_models

        config = config_from_options(ExperimentConfig, options)
        loaded, cluster, results = config.load()
        jobs, launcher, dry_run = config.jobs, config.launcher, config.dry_run
        grid = plan(loaded, results, say=lambda line: typer.echo(line, err=True))  # e.g. a cache's setup adopted
        runs = select(grid, config.only)
        counts = {s: sum(r.status == s for r in runs) for s in ("done", "resume", "new")}
        picked = f"; --only picks {len(runs)} of them" if config.only else ""
        typer.echo(f"{loaded.name}: {counted(len(grid), 'run')} ({counted(len(loaded.envs), 'env')} x "
                   f"{counted(len({r.label for r in grid}), 'configuration')} x {counted(len(loaded.seeds), 'seed')}, "
                   f"{frames_text(loaded)}{picked}): {counts['done']} "
                   f"finished, {counts['resume']} to resume, {counts['new']} to start -> {results}")
        missing = unavailable_models(runs)
        if missing:
            typer.echo("not loadable on this machine offline (`illm models` says why; download them where there is "
                       "network): " + ", ".join(f"{m} ({counted(n, 'run')})" for m, n in missing.items()), err=True)
        if dry_run:
            for r in runs:
                typer.echo(f"  {r.status:6s} {r.config.run_dir}")
            return
        failed = []

        def on_run(run, event: str) -> None:
            typer.echo(f"{event}: {run.env_id} {run.label} seed {run.seed}", err=event != "done")
            if event.startswith("failed"):
                failed.append(run)

        # local runs stop cleanly at a first Ctrl-C; a cluster's jobs run on without this command
        with stop_on_signals("the runs' current updates, then a checkpoint each") if launcher == "local" \
                else nullcontext(Stop()) as stop:
            trained = run_experiment(loaded, results, jobs=jobs, on_run=on_run, launcher=launcher, cluster=cluster,
                                     only=config.only, should_stop=lambda: stop.requested)
        if stop.requested:
            left = [r for r in trained if r.status != "done"]
            typer.echo(f"stopped: {counted(len(left), 'run')} not finished ({sum(r.status == 'stopped' for r in left)} "
                       "with a checkpoint); run the same command again to resume them", err=True)
            raise typer.Exit(stop.exit_code)
        if failed:
            typer.echo(f"{len(failed)} of {len(runs)} runs failed (above); run the same command again to retry them",
                       err=True)
            raise typer.Exit(1)
        rest = len(grid) - len(runs)
        left = f" ({counted(rest, 'run')} of the grid not picked by --only)" if rest else ""
        typer.echo(f"all {counted(len(runs), 'run')} finished{left}: `illm report {results} --out {results}/report` makes the "
                   "tables and plots")

    experiment.__signature__ = inspect.Signature(_parameters())
    app.command(epilog=EXAMPLE)(friendly(experiment))
