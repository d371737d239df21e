"""`illm experiment`: a grid of training runs from a YAML spec, N at a time, resumable."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.errors import friendly


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm experiment experiments/specs/table1.yaml --jobs 2  (then: illm report "
                        "results/table1 --out results/table1/report); on a SLURM cluster: illm experiment "
                        "experiments/specs/table1.yaml --launcher slurm --partition gpu --gpus 1 --jobs 32")
    @friendly
    def experiment(
        spec: Path = typer.Argument(..., help="The experiment's YAML spec (experiments/specs/ has the paper's tables)."),
        out: Path = typer.Option(None, "--out", help="Results folder (default: results/<spec name>)."),
        jobs: int = typer.Option(1, "--jobs", help="Runs trained at a time, each in its own process with one thread."),
        frames: int = typer.Option(None, "--frames", help="Frames per run, over the spec's (the paper: 100000000)."),
        seeds: int = typer.Option(None, "--seeds", help="Seeds 0..N-1, over the spec's (the paper: 10)."),
        dry_run: bool = typer.Option(False, "--dry-run", help="Check the spec and list the runs; train nothing."),
        launcher: str = typer.Option("local", "--launcher",
                                     help="How runs start: local (--jobs processes here), slurm (one job array "
                                          "through submitit, --jobs tasks at a time), submitit-local (the slurm "
                                          "path on this machine, to try it)."),
        partition: str = typer.Option(None, "--partition", help="SLURM partition (over the spec's cluster: block)."),
        time_minutes: int = typer.Option(None, "--time-minutes", help="Time limit of one run's job (default 240)."),
        cpus: int = typer.Option(None, "--cpus", help="CPUs of one run's job, its torch threads (default 1)."),
        gpus: int = typer.Option(None, "--gpus", help="GPUs of one run's job (default 0)."),
        mem_gb: float = typer.Option(None, "--mem-gb", help="Memory of one run's job in GB (default: the "
                                                            "partition's)."),
    ) -> None:
        """Train every run of a spec's grid (methods x envs x settings x seeds) into one results folder;
        finished runs are skipped, unfinished ones resumed, so the same command continues a grid."""
        from illm_tools.errors import UsageError
        from illm_tools.experiment import check_launcher, load_spec, plan, run_experiment
        from illm_tools.settings import check_folder

        if jobs < 1:
            raise UsageError(f"--jobs must be at least 1, got {jobs}")
        check_folder(out, "--out")
        check_launcher(launcher)
        loaded = load_spec(spec, frames=frames, seeds=seeds)
        cluster = loaded.cluster.merged(partition=partition, time_minutes=time_minutes, cpus=cpus, gpus=gpus,
                                        mem_gb=mem_gb)
        results = out or Path("results") / loaded.name
        runs = plan(loaded, results)
        counts = {s: sum(r.status == s for r in runs) for s in ("done", "resume", "new")}
        typer.echo(f"{loaded.name}: {len(runs)} runs ({len(loaded.envs)} envs x {len({r.label for r in runs})} "
                   f"configurations x {len(loaded.seeds)} seeds, {loaded.frames:,} frames each): {counts['done']} "
                   f"finished, {counts['resume']} to resume, {counts['new']} to start -> {results}")
        if dry_run:
            for r in runs:
                typer.echo(f"  {r.status:6s} {r.config.run_dir}")
            return
        failed = []

        def on_run(run, event: str) -> None:
            typer.echo(f"{event}: {run.env_id} {run.label} seed {run.seed}", err=event != "done")
            if event != "done":
                failed.append(run)

        run_experiment(loaded, results, jobs=jobs, on_run=on_run, launcher=launcher, cluster=cluster)
        if failed:
            typer.echo(f"{len(failed)} of {len(runs)} runs failed (above); run the same command again to retry them",
                       err=True)
            raise typer.Exit(1)
        typer.echo(f"all {len(runs)} runs finished: `illm report {results} --out {results}/report` makes the tables "
                   "and plots")
