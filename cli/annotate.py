"""`illm annotate`: annotate a trajectory dataset's states with an LLM, into the shared cache."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.common import API_KEY_ENV, BACKEND, DEVICE, DTYPE, ENDPOINT, MODEL, ORACLE_NOISE, QUANT, progress, stop_on_signals
from cli.errors import friendly


MAX_PROCESSES = 4096
"""More annotating processes than any one launch starts (a typo, not a cluster)."""


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm annotate data/traj/gotolocal --cache data/ann --model smollm2-135m "
                        "--tasks action,summary")
    @friendly
    def annotate(
        data: Path = typer.Argument(..., help="Trajectory dataset written by `illm collect`."),
        cache: Path = typer.Option(Path("data/ann"), "--cache", help="Annotation cache folder (shared across runs)."),
        model: str = MODEL,
        oracle_noise: float = ORACLE_NOISE,
        endpoint: str = ENDPOINT,
        api_key_env: str = API_KEY_ENV,
        tasks: str = typer.Option("action,summary", "--tasks", help="Comma-separated, any combination of action, summary, goal, plan (paper Table 2; goal is also ELLM's)."),
        history: int = typer.Option(3, "--history", help="Observation/action pairs of history in the prompts."),
        layout: str = typer.Option("shared", "--layout", help="Templates: shared (history first, prefix computed once) or paper (as printed)."),
        batch_size: int = typer.Option(8, "--batch-size", help="States per LLM batch."),
        limit: int = typer.Option(None, "--limit", help="Annotate the N most visited distinct states (those not cached yet); the same --limit again annotates nothing."),
        max_minutes: float = typer.Option(None, "--max-minutes", help="Stop after M minutes, keeping every finished chunk; run again to go on."),
        dtype: str = DTYPE,
        quant: str = QUANT,
        mode: str = typer.Option("obs", "--mode", help="obs: the states' text | hop: the raw observations translated into the LLM's embedding space (iLLM(hop); any suite, Atari included)."),
        hop_seed: int = typer.Option(0, "--hop-seed", help="hop: seed of the translation's random projection (the run's --hop-seed)."),
        hop_beta: float = typer.Option(100.0, "--hop-beta", help="hop: inverse temperature of the Hopfield retrieval (the run's --hop-beta)."),
        backend: str = BACKEND,
        device: str = DEVICE,
        num_processes: int = typer.Option(1, "--num-processes", help="Annotate with N processes: runs `accelerate launch --num_processes N` on this command (the states are split between them)."),
    ) -> None:
        """Annotate every distinct state once with the LLM, into the shared cache: its next-action ranking
        and 64-token summary, and the goal and plan tasks when --tasks names them."""
        from illm_tools.annotate.bulk import AnnotateConfig, annotate_dataset, distributed_state
        from illm_tools.errors import UsageError
        from illm_tools.llm.backend import resolve_model

        if not 1 <= num_processes <= MAX_PROCESSES:
            raise UsageError(f"--num-processes must be between 1 and {MAX_PROCESSES:,}, got {num_processes}")

        model = resolve_model(backend, model, oracle_noise=oracle_noise, endpoint=endpoint, api_key_env=api_key_env)
        config = AnnotateConfig(data=data, cache=cache, model=model, tasks=tasks,
                                history=history, layout=layout, batch_size=batch_size, limit=limit, max_minutes=max_minutes,
                                dtype=dtype, quant=quant, obs_mode=mode, hop_seed=hop_seed, hop_beta=hop_beta,
                                device=device, backend=backend)
        if num_processes > 1 and distributed_state() is None:
            raise typer.Exit(launch(num_processes, device))
        state = distributed_state()
        if state is None:
            return annotate_and_report(config)
        try:
            if state.is_main_process:  # one voice: the main process reports
                annotate_and_report(config)
            else:
                annotate_dataset(config)
            state.wait_for_everyone()  # leave together: a gloo group torn down under a peer can abort it
        finally:
            state.destroy_process_group()


def annotate_and_report(config) -> None:
    """The main process's annotation with its progress bar and closing lines."""
    from illm_tools.annotate.bulk import annotate_dataset

    model, cache = config.llm_model, config.cache
    with stop_on_signals("the chunk in progress (written whole)") as stop, \
            progress(0, f"annotate {model}", unit="states") as advance:
        def on_plan(stats, todo: int) -> None:
            typer.echo(f"{stats.states:,} states selected (most visited first), {stats.keys:,} keys: "
                       f"{stats.hits:,} cached, {stats.misses:,} to annotate", err=True)
            advance(0, total=todo)

        def on_progress(n: int, stats) -> None:
            advance(n, stats.states_per_s, hits=stats.hits, misses=stats.misses)

        result = annotate_dataset(config, on_progress=on_progress, on_plan=on_plan,
                                  should_stop=lambda: stop.requested)
    stats = result.stats
    summary = f", summaries {stats.mean_summary_tokens:.1f} tokens on average" if stats.summaries else ""
    typer.echo(
        "nothing to annotate: the cache holds every selected state" if not stats.rows and not stats.stopped_early
        else f"annotated {stats.annotated_states:,} states ({stats.rows:,} rows: "
        + ", ".join(f"{k} {v:,}" for k, v in sorted(stats.per_task.items()))
        + f") in {stats.seconds:.1f}s, {stats.states_per_s:.2f} states/s{summary}"
        + ("" if not stats.stopped_early else "; stopped by a signal, run again to go on" if stop.requested
           else "; stopped at --max-minutes, run again to go on")
    )
    if config.limit is not None:
        typer.echo(f"the {result.selected_states:,} most visited states cover {result.selected_step_share:.0%} "
                   f"of the {result.dataset_steps:,} steps")
    typer.echo(f"the cache now answers {result.covered_states:,} of the {result.dataset_states:,} distinct states "
               f"(history {config.history}), covering {result.covered_step_share:.0%} of the "
               f"{result.dataset_steps:,} steps -> {cache}")
    left = result.dataset_states - result.covered_states
    if left:
        typer.echo(f"left to annotate in this dataset: {left:,} states ({1 - result.covered_step_share:.0%} of its "
                   f"steps); {'run again to go on' if stats.stopped_early else 'a larger --limit takes the next ones'}")
    if config.obs_mode == "obs":
        typer.echo(f"a training run plays new episodes and finds fewer of its states here: `illm data coverage "
                   f"{config.data} --cache {cache} --history {config.history}` estimates how many")
    if stop.requested and stats.stopped_early:
        raise typer.Exit(stop.exit_code)


def launch(num_processes: int, device: str) -> int:
    """Run this same `illm annotate` command under `accelerate launch --multi_gpu` with N processes
    (torchrun underneath; on a machine without GPUs they are CPU processes: accelerate's `--cpu`
    launcher would start one unless MPI is set up). Every launcher setting is given, so accelerate
    asks nothing and warns about nothing. Returns its exit code."""
    import subprocess
    import sys

    argv = sys.argv[1:]
    args, skip = [], False
    for i, arg in enumerate(argv):
        if skip:
            skip = False
            continue
        if arg == "--num-processes":
            skip = True
            continue
        if arg.startswith("--num-processes="):
            continue
        args.append(arg)
    import os

    env = {**os.environ, **({"ACCELERATE_USE_CPU": "true"} if device == "cpu" else {})}
    command = [sys.executable, "-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes", str(num_processes),
               "--num_machines", "1", "--mixed_precision", "no", "--dynamo_backend", "no", "-m", "cli.main", *args]
    return subprocess.run(command, env=env).returncode
