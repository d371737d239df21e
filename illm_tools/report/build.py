"""`illm report --out DIR`: a report folder readable without the toolkit.

DIR/report.md (markdown tables: per env, each configuration's final score as IQM [95% CI] and
mean ± std over seeds; a methods × envs table when there are several envs; what was grouped),
DIR/curves-<env>.png (learning curves with bootstrap bands), DIR/final.png (final scores with
their intervals), DIR/visitation-<env>-<label>.png (per configuration, for runs that saved
visitation.npy, summed over seeds; and bonus-<env>-<label>.png, the bonus paid per visit of each
cell, for runs that saved bonus_visitation.npy), DIR/diagnostics-<env>.png (the bonus's scale,
f^a's agreement and the bonus paid over training, `diagnostics.py`; for a configuration whose seeds
split, its curves and its diagnostics seed by seed in DIR/seeds-<env>-<label>.png and
DIR/seeds-diagnostics-<env>-<label>.png), DIR/quality.png (with probe
files: final score against the annotator's probe agreement, `quality.py`) and DIR/results.json
(every number behind them). With several envs of one score, an aggregate over them: rliable's IQM
over all runs and the probability of improvement over ppo (`aggregate.py`).

A seed's final score is the mean of its last `final_points` curve points (`curves.summarise`: the
points every seed of the row has, so a row's final frame is its shortest seed's last point).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from illm_tools import provenance
from illm_tools.errors import UsageError
from illm_tools.report import plots, stats
from illm_tools.report.achievements import final_achievements
from illm_tools.report.aggregate import aggregate
from illm_tools.report.curves import summarise
from illm_tools.report.diagnostics import diagnostics_png, row_diagnostics, seeds_diagnostics_png
from illm_tools.report.lengths import episode_length
from illm_tools.report.results import read_results

DEFAULT_BOOTSTRAP = 2000
BOOTSTRAP_SEED = 0


def score_name(env_id: str) -> str:
    """The suite's name for its score ("success rate", "Crafter score", "mean return")."""
    from illm_tools.envs import suite_of
    from illm_tools.errors import IllmError

    try:
        return suite_of(env_id).score_name
    except IllmError:  # an env this install does not know: its runs still have a score column
        return "score"


def slug(text: str) -> str:
    """A file-name-safe form of an env id or a row label ("illm (ext_coef 2)" -> "illm-ext_coef-2")."""
    return re.sub(r"[^A-Za-z0-9._=-]+", "-", text).strip("-.") or "run"


def _clean(obj):
    """NaN -> None, numpy scalars -> Python: results.json stays strict JSON."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return None if math.isnan(obj) else float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _row(env_id: str, label: str, group: dict, every: int, final_points: int, reps: int, seed: int) -> dict:
    curves = group["curves"]  # as `summarise` read them: a run still training is read once
    table = np.array([[dict(zip(c.frames, c.success))[f] for f in group["frames"]] for c in curves],
                     dtype=float).reshape(len(curves), len(group["frames"]))
    mean, low, high = stats.curve_band(table, reps, seed)
    finals = stats.final_scores(table, final_points)
    final = stats.iqm_interval(finals, reps, seed)
    used = group["frames"][-final_points:]
    final.update(points=used, frames=used[-1] if used else None,
                 per_seed=[{"seed": c.seed, "run": c.run, "score": s} for c, s in zip(curves, finals.tolist())],
                 no_score=[c.run for c, s in zip(curves, finals) if np.isnan(s)],
                 split=stats.seeds_split(finals, score_name(env_id)))
    if final["split"]:  # its seeds drawn one by one (`plots.seeds_png`): the mean describes none of them
        final["seed_curves"] = [{"seed": c.seed, "points": row} for c, row in zip(curves, table.tolist())]
    trained = {c.run: c.last_step for c in curves} | dict(group["short_runs"])
    return {"env_id": env_id, "label": label, "method": group["method"], "settings": group["settings"],
            "score_name": score_name(env_id),
            "seeds": group["seeds"], "runs": group["runs"], "short_runs": group["short_runs"],
            "trained_frames": trained, "frames": group["frames"], "mean": mean, "std": group["std"],
            "band_low": low, "band_high": high, "final": final, "visitation": None,
            "episode_length": episode_length(curves, group["frames"], final_points, reps, seed,
                                             curves[0].config if curves else {"env_id": env_id}),
            "coverage": group["coverage"] if group["reads_targets"] else None,
            "achievements": final_achievements([c.run for c in curves], [c.seed for c in curves], group["frames"],
                                               every, final_points),
            "provenance": {run: provenance.read(Path(run)) for run in [*group["runs"], *group["short_runs"]]}}


def _png_name(kind: str, row: dict, taken: set[str]) -> str:
    name = f"{kind}-{slug(row['env_id'])}-{slug(row['label'])}"
    while name + ".png" in taken:  # two labels with the same slug
        name += "_"
    taken.add(name + ".png")
    return name + ".png"


def _visitation(row: dict, out: Path, taken: set[str]) -> None:
    from illm_tools.rl.visitation import BONUS_FILE, FILE

    have = [run for run in row["runs"] if (Path(run) / FILE).is_file()]
    if not have:
        return
    name = _png_name("visitation", row, taken)
    grids = [np.load(Path(run) / FILE) for run in have]
    seeds = f"{len(have)} seed{'s' * (len(have) > 1)}"
    plots.visitation_png(grids, out / name, f"{row['env_id']}\n{row['label']}, {seeds} summed")
    row["visitation"] = {"png": name, "runs": have}
    paid = [run for run in have if (Path(run) / BONUS_FILE).is_file()]
    if paid:
        name = _png_name("bonus", row, taken)
        plots.bonus_png([np.load(Path(run) / FILE) for run in paid], [np.load(Path(run) / BONUS_FILE) for run in paid],
                        out / name, f"{row['env_id']}\n{row['label']}: bonus paid per visit, {len(paid)} seeds")
        row["bonus_map"] = {"png": name, "runs": paid}


def build_report(run_dirs: list[Path], out: Path, every: int, final_points: int = 1,
                 reps: int = DEFAULT_BOOTSTRAP, seed: int = BOOTSTRAP_SEED, probes: list[Path] = (),
                 groups: dict | None = None) -> dict:
    """Write the report folder `out` (see the module docstring) and return results.json's content.
    `probes` (`illm probe --out` files) add the annotator-quality curve (`illm_tools.report.quality`);
    `groups`: `summarise`'s of the same runs where the caller has read them already."""
    from illm_tools.report.quality import load_probes

    if final_points <= 0:
        raise UsageError(f"--final-points must be at least 1, got {final_points}")
    if reps <= 0:
        raise UsageError(f"--bootstrap must be at least 1 resample, got {reps}")
    probe_figures = load_probes(list(probes))
    groups = summarise(list(run_dirs), every) if groups is None else groups
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file: pass a folder for the report")
    out.mkdir(parents=True, exist_ok=True)
    rows = [_row(env, label, g, every, final_points, reps, seed) for (env, label), g in groups.items()]
    envs = list(dict.fromkeys(r["env_id"] for r in rows))
    taken: set[str] = set()
    for row in rows:
        row["bonus_map"] = None
        _visitation(row, out, taken)
        row["diagnostics"] = row_diagnostics(row, every)
    quality_result = None
    if probe_figures:
        from illm_tools.report.quality import quality

        from illm_tools.rl.saved import read_run

        configs = {key: read_run(Path(g["runs"][0])).settings for key, g in groups.items() if g["runs"]}
        quality_result = quality([r for r in rows if (r["env_id"], r["label"]) in configs], configs, probe_figures)
        if not quality_result["points"]:
            import logging

            logging.getLogger(__name__).warning(
                "no configuration here has both a final score (an episode ended in its last points) and a probed "
                "annotator (the same env, backend, model, history and layout as a --probe file), so quality.png is "
                "not drawn; the probes stay in results.json")
    settings = {"every": every, "final_points": final_points, "bootstrap_reps": reps, "bootstrap_seed": seed,
                "code": provenance.code(), "command": provenance.command(), "confidence": stats.CONFIDENCE, "interval": "percentile, stratified bootstrap over seeds (rliable)"}
    return _write(out, settings, envs, rows, quality_result, aggregate(rows, envs, reps, seed))


def _figures(out: Path, envs: list[str], rows: list[dict], quality_result: dict | None) -> dict:
    """Draw the curves, final-score and quality figures of `rows` into `out`; their file names."""
    curve_files = {}
    # one colour per line (a method and its settings other than the panels') in every figure
    colour = plots.colours(list(dict.fromkeys(line for env in envs for _, line in
                                              plots.panels([r for r in rows if r["env_id"] == env])[1])))
    for env in envs:
        plotted = [r for r in rows if r["env_id"] == env and r["frames"]]
        if not plotted:  # every run of the env too short for a point
            continue
        name = f"curves-{slug(env)}.png"
        plots.curves_png(env, score_name(env), plotted, out / name, colour)
        curve_files[env] = name
    panels = [{"env_id": env, "score_name": score_name(env), "rows": [r for r in rows if r["env_id"] == env]}
              for env in envs]
    final_file = None
    if any(r["final"]["iqm"] is not None for r in rows):
        final_file = "final.png"
        plots.final_png(panels, out / final_file, colour)
    quality_file = None
    if quality_result and quality_result.get("points"):
        from illm_tools.report.quality import quality_png

        quality_file = "quality.png"
        quality_png(quality_result, {env: score_name(env) for env in envs}, out / quality_file)
    seed_files, seed_diagnostics_files, taken = {}, {}, set()
    for row in rows:  # a configuration whose seeds split: its curves and its diagnostics seed by seed
        key = f"{row['env_id']} / {row['label']}"
        if row["final"].get("seed_curves"):
            seed_files[key] = _png_name("seeds", row, taken)
            plots.seeds_png(row, out / seed_files[key])
        if (row.get("diagnostics") or {}).get("per_seed"):
            seed_diagnostics_files[key] = _png_name("seeds-diagnostics", row, taken)
            seeds_diagnostics_png(row, out / seed_diagnostics_files[key])
    diagnostics_files = {}
    for env in envs:
        shown = [r for r in rows if r["env_id"] == env and r.get("diagnostics")]
        if shown:
            diagnostics_files[env] = f"diagnostics-{slug(env)}.png"
            diagnostics_png(env, shown, out / diagnostics_files[env], colour)
    return {"report": "report.md", "curves": curve_files, "final": final_file, "quality": quality_file,
            "diagnostics": diagnostics_files, "seeds": seed_files, "seeds_diagnostics": seed_diagnostics_files,
            "visitation": {f"{r['env_id']} / {r['label']}": r["visitation"]["png"] for r in rows if r["visitation"]}}


def _write(out: Path, settings: dict, envs: list[str], rows: list[dict], quality_result: dict | None,
           across: dict | None = None) -> dict:
    """Figures, report.md and results.json of a report into `out`; returns results.json's content."""
    from illm_tools.report.markdown import render

    results = _clean({"settings": settings, "envs": envs, "rows": rows, "quality": quality_result,
                      "aggregate": across, "files": _figures(out, envs, rows, quality_result)})
    from illm_tools import durable

    durable.write_text(out / "report.md", render(results))
    durable.write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    return results


def merge_reports(parts: list[Path], out: Path) -> dict:
    """Write the report folder `out` from the report folders `parts` (`ReportConfig.merge`): their rows
    as they are, the heatmaps copied beside them, the aggregate over every env computed afresh with the
    parts' bootstrap settings. Hand-written rather than re-reading the runs: a grid run in parts over
    several sessions keeps its reports, not always its runs. Each part's results.json is checked
    (`results.check_results`: its shape, and every heatmap it names a bare name inside the part)
    before anything is written, and the commands it recorded are redacted again."""
    from illm_tools import durable

    out = Path(out)
    loaded = []
    for part in map(Path, parts):
        results = read_results(part, "--merge takes report folders")
        loaded.append((part, results["settings"], results["envs"], results["rows"]))
    keys = ("every", "final_points", "bootstrap_reps", "bootstrap_seed")
    first = loaded[0][1]
    for part, settings, _, _ in loaded[1:]:
        differ = [k for k in keys if settings.get(k) != first.get(k)]
        if differ:
            raise UsageError(f"{part} was reported with other {', '.join(differ)} than {loaded[0][0]}: write the "
                             f"parts' reports again with the same --every, --final-points and --bootstrap")
    envs: list[str] = []
    for part, _, part_envs, _ in loaded:
        twice = [e for e in part_envs if e in envs]
        if twice:
            raise UsageError(f"{twice[0]} is in two of the parts ({part} and an earlier one): report each env in one "
                             "part, or report its runs together")
        envs += part_envs
    if any(out.resolve() == part.resolve() for part, *_ in loaded):
        raise UsageError("--out is one of the parts: pass a new folder for the joined report")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for part, _, _, part_rows in loaded:
        for row in part_rows:
            for name in ("visitation", "bonus_map"):
                if row.get(name):
                    png = part / row[name]["png"]  # a bare name (`read_results`): inside the part, copied inside out
                    if png.is_file() and not png.is_symlink():
                        durable.write_bytes(out / png.name, png.read_bytes())
                    else:
                        row[name] = None
            rows.append(row)
    settings = {**{k: first[k] for k in keys}, "code": provenance.code(), "command": provenance.command(),
                "confidence": first.get("confidence", stats.CONFIDENCE), "interval": first.get("interval"),
                "parts": [{"folder": str(part), "command": s.get("command"), "code": s.get("code")}
                          for part, s, _, _ in loaded]}
    return _write(out, settings, envs, rows, None,
                  aggregate(rows, envs, first["bootstrap_reps"], first["bootstrap_seed"]))


def _number(text: str):
    """A setting parsed from a label as the config held it: "16" -> 16, "0.5" -> 0.5, else the text."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


_LABEL = re.compile(r"^(?P<method>[^ ]+)(?: \((?P<settings>.*)\))?$")


def redraw_report(folder: str | Path) -> dict:
    """Draw a report folder's figures and report.md again from its results.json, with this
    version's figures (small multiples, rliable's final-score plot): for a report whose run folders
    are gone. Visitation heatmaps need the runs' counts and are kept as they are. A row of an older
    report without its settings gets them from its label ("illm (num_dists 16)")."""
    folder = Path(folder)
    results = read_results(folder, "--redraw takes a report folder")
    rows, envs, settings = results["rows"], results["envs"], results["settings"]
    for row in rows:
        if row.get("settings") is None:
            parsed = _LABEL.match(row["label"])
            pairs = [p.strip().split(" ", 1) for p in (parsed["settings"] or "").split(",") if p.strip()] \
                if parsed else []
            row["settings"] = {k: _number(v) for k, *rest in pairs for v in rest}
        for name in ("visitation", "bonus_map"):
            if row.get(name) and not (folder / row[name]["png"]).is_file():
                row[name] = None  # its heatmap is gone and cannot be drawn again without the runs
    return _write(folder, settings, envs, rows, results.get("quality"), results.get("aggregate"))
