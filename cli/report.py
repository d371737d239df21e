"""`illm report`: success-rate curves of training runs, grouped by method over seeds."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.common import emit_json
from cli.errors import friendly


def register(app: typer.Typer) -> None:
    @app.command(epilog="Example: illm report runs/gotolocal-* --every 20000 --out reports/gotolocal")
    @friendly
    def report(
        runs: list[Path] = typer.Argument(..., help="Run folders written by `illm train`, or folders holding them (an `illm experiment` results folder)."),
        every: int = typer.Option(20_000, "--every", help="Frames per curve point (window of the score)."),
        as_json: bool = typer.Option(False, "--json", help="Print machine-readable JSON."),
        out: Path | None = typer.Option(None, "--out", help="Also write a report folder: report.md (IQM [95% CI] "
                                        "and mean ± std per configuration), learning-curve and visitation PNGs, "
                                        "results.json."),
        final_points: int = typer.Option(1, "--final-points", help="With --out: a seed's final score is the mean "
                                         "of its last this many curve points."),
        bootstrap: int = typer.Option(2000, "--bootstrap", help="With --out: bootstrap resamples of the 95% "
                                      "intervals (rliable's stratified bootstrap, seeded)."),
        probe: list[Path] = typer.Option(None, "--probe", help="With --out: an `illm probe --out` file "
                                         "(repeatable): final score against the annotator's probe agreement "
                                         "(quality.png); probes of models not trained with are marked on it."),
        redraw: bool = typer.Option(False, "--redraw", help="Draw a report folder's figures and report.md again "
                                    "from its results.json (the runs may be gone; heatmaps are kept): "
                                    "`illm report docs/results/table1 --redraw`."),
    ) -> None:
        """The suite's score against frames (success rate; Crafter score; Atari's mean return), mean ±
        std over seeds, one row per configuration (a markdown table), then what was grouped: runs
        are seeds of one row when their config.json agree on everything that changes what is learned.
        With --out, also a report folder readable without the toolkit: final scores as IQM with a
        stratified-bootstrap 95% interval over seeds (rliable) and mean ± std, learning curves with
        bands, visitation heatmaps where runs saved visitation.npy, and results.json."""
        from illm_tools.envs import suite_of
        from illm_tools.report.curves import summarise

        from illm_tools.errors import UsageError

        if redraw:
            from illm_tools.report.build import redraw_report

            if len(runs) != 1 or out is not None or probe:
                raise UsageError("--redraw takes one report folder and no --out or --probe: `illm report DIR --redraw`")
            redraw_report(runs[0])
            typer.echo(f"report redrawn in {runs[0] / 'report.md'} (figures beside it)")
            return
        if every <= 0 or final_points <= 0 or bootstrap <= 0:
            raise UsageError(f"--every, --final-points and --bootstrap must be positive, got {every}, {final_points} "
                             f"and {bootstrap}")
        if out is not None and out.exists() and not out.is_dir():
            raise UsageError(f"--out {out} is a file: pass a folder for the report")
        missing = [str(r) for r in runs if not r.is_dir()]
        if missing:
            raise UsageError(f"no run folder at {', '.join(missing[:3])}: pass folders written by `illm train`")
        # a folder that is not a run (an `illm experiment` results folder) stands for the runs below it
        runs = [run for r in runs for run in ([r] if (r / "metrics.csv").is_file() or (r / "config.json").is_file()
                                             else sorted(p.parent for p in r.rglob("metrics.csv")))]
        if not runs:
            raise UsageError("no training run in the folders given: pass folders written by `illm train` or "
                             "`illm experiment`")
        groups = summarise(list(runs), every)
        if out is not None:
            from illm_tools.report.build import build_report

            build_report(list(runs), out, every, final_points=final_points, reps=bootstrap, probes=probe or [])
        elif probe:
            raise UsageError("--probe adds the quality curve to a report folder: pass --out DIR too")
        written = f"report written to {out / 'report.md'} (figures and results.json beside it)" if out else ""
        if as_json:
            emit_json([{"env_id": env, "label": label, **g} for (env, label), g in groups.items()])
            if written:
                typer.echo(written, err=True)
            return
        frames = max((g["frames"] for g in groups.values()), key=len, default=[])
        typer.echo("| env | method | seeds | " + " | ".join(f"{f:,}" for f in frames)
                   + " | steps with a target |")
        typer.echo("|---" * (4 + len(frames)) + "|")
        for (env, method), g in groups.items():
            by_frame = dict(zip(g["frames"], zip(g["mean"], g["std"])))
            cells = ["-" if f not in by_frame or by_frame[f][0] != by_frame[f][0]  # nan: no episode ended there
                     else f"{by_frame[f][0]:.2f}" if len(g["seeds"]) < 2  # one seed: no spread to show
                     else f"{by_frame[f][0]:.2f} ± {by_frame[f][1]:.2f}" for f in frames]
            cover = f"{g['coverage']:.1%}" if g["reads_targets"] else "-"
            typer.echo(f"| {env} | {method} | {len(g['seeds'])} | " + " | ".join(cells) + f" | {cover} |")
        typer.echo("")
        for (env, method), g in groups.items():
            typer.echo(f"{env}, {method} ({suite_of(env).score_name}): seeds {', '.join(map(str, g['seeds'])) or '-'} "
                       f"({', '.join(g['runs']) or 'no run'})")
            for run, last in g["short_runs"].items():
                typer.echo(f"  {run} left out: trained for {last:,} frames, too short for a point at --every "
                           f"{every:,} (a run gives a last, shorter window once it passes half of it)")
        if written:
            typer.echo(f"\n{written}")
