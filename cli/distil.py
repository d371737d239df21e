"""`illm distil`: fine-tune a small causal LM on a cache's annotations into a student annotator."""

from __future__ import annotations

import inspect
from contextlib import ExitStack

import typer

from cli.common import progress, stop_on_signals
from cli.errors import friendly

EXAMPLE = ("Example: illm distil data/ann-oracle --student smollm2-135m --out models/smollm2-135m-babyai; "
           "then illm probe --env BabyAI-UnlockLocal-v0 --model models/smollm2-135m-babyai")
PHASES = {"base": ("base model on the held-out states", "states"), "train": ("distil", "steps"),
          "student": ("student on the held-out states", "states")}


def _parameters() -> list[inspect.Parameter]:
    """`DistilConfig`'s fields as options (`cli.options`), the cache positional."""
    from cli.options import dataclass_parameters
    from illm_tools.distil.config import DistilConfig

    return dataclass_parameters(DistilConfig, arguments={"cache"}, required={"out"})


def register(app: typer.Typer) -> None:
    def distil(**options) -> None:
        """Fine-tune a small causal LM on a teacher's annotations into a student annotator.

        LoRA adapters, merged; the student learns from the cache to rank the valid actions as the teacher
        did, through the annotator's own candidate scoring, and to write its texts.
        Checkpoints as it goes; the same command again resumes. The student is a model folder: --model OUT."""
        from cli.options import config_from_options
        from illm_tools.distil.config import DistilConfig
        from illm_tools.distil.run import distil as run

        config = config_from_options(DistilConfig, options)
        with stop_on_signals("the step in progress, then a checkpoint") as stop, ExitStack() as bar:
            current: dict = {}

            def on_progress(phase: str, n: int, total: int | None = None, **figures) -> None:
                if current.get("phase") != phase:  # one bar per phase: the last one closes, the next opens
                    bar.close()
                    title, unit = PHASES[phase]
                    current.update(phase=phase, advance=bar.enter_context(progress(total or 0, title, unit=unit)))
                current["advance"](n, total=total, **figures)

            result = run(config, on_progress=on_progress, should_stop=lambda: stop.requested)
        _report(config, result, stop)

    distil.__signature__ = inspect.Signature(_parameters())
    app.command(epilog=EXAMPLE)(friendly(distil))


def _report(config, result, stop) -> None:
    from cli.common import _duration

    if result.stopped:
        why = "by a signal" if stop.requested else "at --max-minutes"
        typer.echo(f"stopped {why} at step {result.steps_done:,} of {result.steps:,} (a checkpoint is written): run the "
                   "same command again to go on")
        if stop.requested:
            raise typer.Exit(stop.exit_code)
        return
    if result.already:
        typer.echo(f"{config.out} already holds this student: nothing to train (its figures below)")
    m = result.machine
    rank = f"LoRA rank {config.rank}, merged" if config.rank else "every weight"
    rank += f", top {config.layers} blocks" if config.layers else ""
    rank += f", {config.blocks} of its blocks kept" if config.blocks else ""
    typer.echo(f"distilled {result.teacher}'s {','.join(config.tasks)} into {result.out} ({result.base}, {rank}): "
               f"{result.train_states:,} training states, {result.held_out_states:,} held out"
               + (f", {result.left_out_long:,} longer than --max-tokens left out" if result.left_out_long else "")
               + f"; {result.steps:,} steps"
               + (f" in {_duration(result.train_seconds)} ({result.train_tokens_per_s:,.0f} tokens/s, {m.get('dtype')}, "
                  f"{m.get('threads')} threads)" if result.train_seconds else "")
               + (f", resumed from step {result.resumed_from:,} (the time and rate over every session)"
                  if result.resumed_from else ""))
    if result.log_history:
        typer.echo(f"training loss {result.loss_first:.3f} -> {result.loss_last:.3f} (mean of the first and the last "
                   "tenth of the steps)")
    b, s = result.base_measure, result.student_measure
    if s.get("states"):
        texts = (f"; the teacher's texts: {b['text_nll']:.3f} -> {s['text_nll']:.3f} nats/token"
                 if s.get("text_nll") else "")
        base = "base, its kept blocks" if config.blocks else "base"
        typer.echo(f"held-out states ({s['states']:,}): agreement with the teacher's top action {b['agreement']:.3f} "
                   f"({base}) -> {s['agreement']:.3f} (student); KL from the teacher's distribution "
                   f"{b['ranking_kl']:.3f} -> {s['ranking_kl']:.3f} nats{texts}")
    typer.echo(f"the student loads with --model {result.out} (fingerprint {result.student_fingerprint[:12]}, its base's "
               f"{result.base_fingerprint[:12]}); wall time {_duration(result.wall_seconds)}; figures in "
               f"{result.out}/distil/report.json")
