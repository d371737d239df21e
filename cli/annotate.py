"""`illm annotate`: annotate a trajectory dataset's states with an LLM, into the shared cache."""

from __future__ import annotations

import inspect

import typer

from cli.common import progress, stop_on_signals
from cli.errors import friendly

EXAMPLE = "Example: illm annotate data/traj/gotolocal --cache data/ann --model smollm2-135m --tasks action,summary"


def _parameters() -> list[inspect.Parameter]:
    """`AnnotateConfig`'s fields as options (`cli.options`; its LLM's as --backend, --model, ...)."""
    from cli.options import dataclass_parameters
    from illm_tools.annotate.bulk import AnnotateConfig

    return dataclass_parameters(AnnotateConfig, arguments={"data"},
                                extra_help={"tasks": "(paper Table 2; goal is also ELLM's)."})


def register(app: typer.Typer) -> None:
    def annotate(**options) -> None:
        """Annotate every distinct state once with the LLM, into the shared cache.

        What it stores: the LLM's next-action ranking and 64-token summary, and the goal and plan tasks
        when --tasks names them."""
        from cli.options import config_from_options
        from illm_tools.annotate.bulk import AnnotateConfig, annotate_dataset, distributed_state

        config = config_from_options(AnnotateConfig, options)
        if config.num_processes > 1 and distributed_state() is None:
            raise typer.Exit(launch(config.num_processes, config.llm.device))
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

    annotate.__signature__ = inspect.Signature(_parameters())
    app.command(epilog=EXAMPLE)(friendly(annotate))


def annotate_and_report(config) -> None:
    """The main process's annotation with its progress bar and closing lines."""
    from illm_tools.annotate.bulk import annotate_dataset

    model, cache = config.llm.model, config.cache
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
    if stats.too_long:
        shown = "; ".join(f"#{rank + 1:,} of {env} ({tokens:,} tokens)" for rank, env, tokens in stats.too_long[:5])
        typer.echo(f"skipped {len(stats.too_long):,} states longer than the model's context (most visited first): "
                   f"{shown}{' ...' if len(stats.too_long) > 5 else ''}; a shorter --history, or a model of a longer "
                   "context, takes them")
    if config.limit is not None:
        typer.echo(f"the {result.selected_states:,} most visited states cover {result.selected_step_share:.0%} "
                   f"of the {result.dataset_steps:,} steps")
    typer.echo(f"the cache now answers {result.covered_states:,} of the {result.dataset_states:,} distinct states "
               f"(history {config.setup.history_len}), covering {result.covered_step_share:.0%} of the "
               f"{result.dataset_steps:,} steps -> {cache}")
    left = result.dataset_states - result.covered_states
    if left:
        typer.echo(f"left to annotate in this dataset: {left:,} states ({1 - result.covered_step_share:.0%} of its "
                   f"steps); {'run again to go on' if stats.stopped_early else 'a larger --limit takes the next ones'}")
    if not config.setup.hop:
        from illm_tools.llm.spec import LLMSpec

        model = "" if config.llm == LLMSpec(device=config.llm.device) else f" {config.llm.options()}"
        tasks = "" if config.tasks == ("action", "summary") else f" --tasks {','.join(config.tasks)}"
        typer.echo(f"a training run plays new episodes and finds fewer of its states here: `illm data coverage "
                   f"{config.data} --cache {cache} {config.setup.options()}{model}{tasks}` estimates how many")
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
