"""`illm report`: success-rate curves of training runs, grouped by method over seeds."""

from __future__ import annotations

import inspect

import typer

from cli.common import emit_json
from cli.errors import friendly


def _parameters() -> list[inspect.Parameter]:
    from cli.options import dataclass_parameters
    from illm_tools.report.config import ReportConfig

    as_json = inspect.Parameter("as_json", inspect.Parameter.KEYWORD_ONLY, annotation=bool,
                                default=typer.Option(False, "--json", help="Print machine-readable JSON."))
    return dataclass_parameters(ReportConfig, arguments={"runs"}) + [as_json]


def register(app: typer.Typer) -> None:
    def report(**options) -> None:
        """Report runs: the score against frames over seeds, one row per configuration.

        The suite's score (success rate; Crafter score; Atari's mean return), mean ± std over seeds, one
        row per configuration (a markdown table), then what was grouped: runs are seeds of one row when
        their config.json agree on everything that changes what is learned.
        With --out, also a report folder readable without the toolkit: final scores as IQM with a
        stratified-bootstrap 95% interval over seeds (rliable) and mean ± std, learning curves with
        bands, visitation heatmaps where runs saved visitation.npy, and results.json."""
        from cli.options import config_from_options
        from illm_tools.envs import suite_of
        from illm_tools.report.config import ReportConfig
        from illm_tools.report.curves import summarise

        as_json = options.pop("as_json")
        config = config_from_options(ReportConfig, options)
        if config.redraw:
            from illm_tools.report.build import redraw_report

            redraw_report(config.runs[0])
            typer.echo(f"report redrawn in {config.runs[0] / 'report.md'} (figures beside it)")
            return
        if config.merge:
            from illm_tools.report.build import merge_reports

            merge_reports(list(config.runs), config.out)
            typer.echo(f"report written to {config.out / 'report.md'} from {len(config.runs)} reports (figures and "
                       "results.json beside it)")
            return
        runs, every, out = config.run_folders(), config.every, config.out
        groups = summarise(list(runs), every)
        if out is not None:
            from illm_tools.report.build import build_report

            build_report(list(runs), out, every, final_points=config.final_points, reps=config.bootstrap,
                         probes=config.probe, groups=groups)  # the runs read once: a grid still training agrees
        written = f"report written to {out / 'report.md'} (figures and results.json beside it)" if out else ""
        if as_json:
            emit_json([{"env_id": env, "label": label, **{k: v for k, v in g.items() if k != "curves"}}
                       for (env, label), g in groups.items()])
            if written:
                typer.echo(written, err=True)
            return
        frames = max((g["frames"] for g in groups.values()), key=len, default=[])
        if not frames:
            typer.echo(f"no run has trained for half of --every {every:,} frames, so there is no curve point to show: "
                       "pass a smaller --every", err=True)
        header = ["env", "method", "seeds", *(f"{f:,}" for f in frames), "steps with a target"]
        typer.echo("| " + " | ".join(header) + " |")
        typer.echo("|---" * len(header) + "|")
        for (env, method), g in groups.items():
            by_frame = dict(zip(g["frames"], zip(g["mean"], g["std"])))
            cells = ["-" if f not in by_frame or by_frame[f][0] != by_frame[f][0]  # nan: no episode ended there
                     else f"{by_frame[f][0]:.2f}" if len(g["seeds"]) < 2  # one seed: no spread to show
                     else f"{by_frame[f][0]:.2f} ± {by_frame[f][1]:.2f}" for f in frames]
            cover = f"{g['coverage']:.1%}" if g["reads_targets"] else "-"
            typer.echo("| " + " | ".join([env, method, str(len(g["seeds"])), *cells, cover]) + " |")
        typer.echo("")
        for (env, method), g in groups.items():
            typer.echo(f"{env}, {method} ({suite_of(env).score_name}): seeds {', '.join(map(str, g['seeds'])) or '-'} "
                       f"({', '.join(g['runs']) or 'no run'})")
            for run, last in g["short_runs"].items():
                typer.echo(f"  {run} left out: trained for {last:,} frames, too short for a point at --every "
                           f"{every:,} (a run gives a last, shorter window once it passes half of it)")
        if written:
            typer.echo(f"\n{written}")

    report.__signature__ = inspect.Signature(_parameters())
    app.command(epilog="Example: illm report runs/gotolocal-* --every 20000 --out reports/gotolocal")(friendly(report))
