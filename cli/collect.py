"""`illm collect`: log trajectories of a policy to an Arrow dataset. Its options are generated from
`illm_tools.collect.CollectConfig` (`cli.options`): one per field, named, defaulted and documented
as the field."""

from __future__ import annotations

import inspect
import time

import typer

from cli.common import progress, score_text, write_mode
from cli.errors import friendly

EXAMPLE = ("Example: illm collect --env BabyAI-GoToLocal-v0 --steps 20000 --out data/traj/gotolocal --seed 0  |  "
           "illm collect --env CrafterReward-v1 --steps 5000 --out data/traj/crafter  (`illm envs` lists every env)")


def _parameters() -> list[inspect.Parameter]:
    from cli.options import dataclass_parameters
    from illm_tools.collect import CollectConfig

    params = dataclass_parameters(CollectConfig, exclude={"write"},
                                  defaults={}, required={"env_id", "out"},
                                  extra_help={"env_options": "E.g. max_episode_steps=500."})
    flags = [("append", "--append", "Add to an existing dataset at --out."),
             ("overwrite", "--overwrite", "Replace the dataset at --out (only once the new one is complete).")]
    return params + [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=bool,
                                       default=typer.Option(False, decl, help=text)) for name, decl, text in flags]


def register(app: typer.Typer) -> None:
    def collect(**options) -> None:
        """Collect trajectories with a policy into an Arrow dataset (one row per step)."""
        from cli.options import config_from_options
        from illm_tools.collect import CollectConfig
        from illm_tools.collect import collect as run

        write = write_mode(options.pop("append"), options.pop("overwrite"))
        config = config_from_options(CollectConfig, {**options, "write": write})
        start = time.perf_counter()
        with progress(config.steps, f"collect {config.env_id}") as advance:
            done = [0]

            def on_progress(n: int, stats: dict) -> None:
                done[0] += n
                rate = done[0] / max(time.perf_counter() - start, 1e-9)
                advance(n, rate, episodes=stats["episodes"], score=score_text(stats["score"]))

            summary = run(config, on_progress)
        seconds = time.perf_counter() - start
        ret = f", mean return {summary['mean_return']:.3f}" if summary["score_name"] != "mean return" else ""
        running = summary["episodes_running"]
        typer.echo(
            f"collected {summary['rows']:,} steps, {summary['episodes_finished']:,} finished episodes "
            f"({summary['score_name']} {score_text(summary['score'])}{ret}) and {running:,} still running at the end, "
            f"from {config.env_id} ({summary['action_space']} actions) with policy {summary['policy']} in "
            f"{seconds:.1f}s -> {summary['out']}"
        )
        if summary["biased"]:
            typer.echo(f"warning: only {summary['episodes_finished']:,} episodes finished beside the {running:,} still "
                       f"running: the quick ones finish first, so the {summary['score_name']} above leans toward them "
                       "(a longer episode, often a failure, has not ended yet); a larger --steps reads it fairly",
                       err=True)

    collect.__signature__ = inspect.Signature(_parameters())
    app.command(epilog=EXAMPLE)(friendly(collect))
