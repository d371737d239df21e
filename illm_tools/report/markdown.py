"""report.md from results.json's content (`build.build_report`): plain markdown, no toolkit needed."""

from __future__ import annotations

from illm_tools import provenance
from illm_tools.report.achievements import achievements_section


def num(x) -> str:
    """A score: 3 decimals (success rates, Crafter scores), 1 from 100 on (Atari returns)."""
    if x is None:
        return "-"
    return f"{x:.3f}" if abs(x) < 100 else f"{x:.1f}"


def beats(mine: float, other: float) -> bool:
    """The tie rule of the pages' verdict words (docs/render.py says why): `mine` beats `other` when it is
    higher as printed (`num`, 3 decimals); two values that print the same are a tie, which neither beats."""
    return float(num(mine)) > float(num(other))


def steps(x) -> str:
    """An episode length: 1 decimal."""
    return "-" if x is None else f"{x:.1f}"


def iqm_cell(final: dict, fmt=num) -> str:
    if final["iqm"] is None:
        return "-"
    if final["ci_low"] is None:
        return f"{fmt(final['iqm'])} (1 seed: no interval)"
    return f"{fmt(final['iqm'])} [{fmt(final['ci_low'])}, {fmt(final['ci_high'])}]"


def mean_cell(final: dict, fmt=num) -> str:
    if final["mean"] is None:
        return "-"
    return fmt(final["mean"]) if final["n"] < 2 else f"{fmt(final['mean'])} ± {fmt(final['std'])}"


def _esc(text: str) -> str:
    return str(text).replace("|", "\\|")


def _frames(n) -> str:
    return "-" if n is None else f"{n:,}"


def _split(label: str) -> tuple[str, str]:
    """"illm (num_dists 4)" -> ("illm", "num_dists 4"); "ppo" -> ("ppo", "")."""
    method, _, rest = label.partition(" (")
    return method, rest[:-1] if rest.endswith(")") else rest


def _banded(row: dict) -> bool:
    """The row's learning curve has a bootstrap band somewhere (several seeds at some frame)."""
    return any(v is not None and v == v for v in row.get("band_low") or ())


def _table(header: list[str], lines: list[list[str]]) -> list[str]:
    return (["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
            + ["| " + " | ".join(_esc(c) for c in line) + " |" for line in lines])


def _env_section(env: str, rows: list[dict], settings: dict, curves_png: str | None,
                 diagnostics_png: str | None = None) -> list[str]:
    score, k = rows[0]["score_name"], settings["final_points"]
    out = [f"## {env} ({score})", "",
           f"Final {score}: each seed's mean over its last {k} curve point{'s' * (k > 1)} (windows of "
           f"{settings['every']:,} frames), at the frames given. IQM [95% CI]: interquartile mean over seeds with a "
           f"stratified-bootstrap percentile interval (rliable, {settings['bootstrap_reps']:,} resamples, seed "
           f"{settings['bootstrap_seed']}); mean ± std (population std) over seeds beside it. With one seed no "
           "interval can be computed and the single value is shown.", ""]
    covered = any(r.get("coverage") is not None for r in rows)  # the share of steps with a target, where read
    out += _table(["method", "IQM [95% CI]", "mean ± std", "seeds", "frames"] + ["target coverage"] * covered,
                  [[r["label"], iqm_cell(r["final"]), mean_cell(r["final"]), str(r["final"]["n"]),
                    _frames(r["final"]["frames"])]
                   + ["-" if r.get("coverage") is None else f"{r['coverage']:.0%}"] * covered for r in rows])
    out += split_section(rows, settings)
    out += length_section(rows, k)
    out += achievements_section(rows)
    split = [_split(r["label"]) for r in rows]
    from illm_tools.report.plots import setting_order

    order = {}
    for (_, column), r in zip(split, rows):  # a column's settings' values, numbers by value (4, 8, 16)
        order.setdefault(column, tuple(setting_order(v) for _, v in sorted(r.get("settings", {}).items())))
    columns = sorted(dict.fromkeys(s for _, s in split), key=lambda c: (c == "", order[c]))  # "(as is)" last
    methods = list(dict.fromkeys(m for m, _ in split))
    if len(columns) > 1 and len(methods) < len(rows):  # settings shared by methods: the paper's method x setting grid
        cells = {sp: iqm_cell(r["final"]) for sp, r in zip(split, rows)}
        out += ["", f"The same, methods × settings (IQM [95% CI] of the final {score}):", ""]
        out += _table(["method"] + [c or "(as is)" for c in columns],
                      [[m] + [cells.get((m, c), "-") for c in columns] for m in methods])
    if curves_png:
        out += ["", f"![{score} against frames, {env}]({curves_png})", "",
                f"Learning curves ({curves_png}): mean over seeds, "
                + ("shaded: pointwise 95% bootstrap band." if any(_banded(r) for r in rows)
                   else "no band: one seed per line, nothing to bootstrap over.")]
    heatmaps = [r for r in rows if r["visitation"]]
    if heatmaps:
        out += ["", "Visitation (visits per cell, summed over seeds, log colour scale):", ""]
        for r in heatmaps:
            n = len(r["visitation"]["runs"])
            out += [f"- {_esc(r['label'])} ({n} of {len(r['runs'])} seeds saved visitation.npy): "
                    f"![visitation, {_esc(r['label'])}]({r['visitation']['png']})"]
    paid = [r for r in rows if r.get("bonus_map")]
    if paid:
        out += ["", "Where the bonus was paid (the bonus paid per visit of each cell, seeds summed):", ""]
        out += [f"- {_esc(r['label'])}: ![bonus, {_esc(r['label'])}]({r['bonus_map']['png']})" for r in paid]
    return out + diagnostics_section(rows, diagnostics_png) + [""]


def split_section(rows: list[dict], settings: dict) -> list[str]:
    """The configurations whose seeds split (`stats.seeds_split`: some near 0, others solving the
    level), each with its seeds' finals, its per-seed figure and, where it logged them, its diagnostics
    seed by seed: the interval above hides them."""
    from illm_tools.report.stats import SPLIT_HIGH, SPLIT_LOW, seeds_split

    split = [r for r in rows if r["final"].get("split", seeds_split([s["score"] for s in r["final"].get("per_seed", [])],
                                                                     r["score_name"]))]
    if not split:
        return []
    out = ["", f"**Seeds that split** (some end at or below {SPLIT_LOW:g}, others at or above {SPLIT_HIGH:g}): "
           "an IQM and its interval over such seeds describe none of them; read the seeds.", ""]
    figures, diagnosed = settings.get("seed_figures", {}), settings.get("seed_diagnostics_figures", {})
    keys = [f"{r['env_id']} / {r['label']}" for r in split]
    for r, key in zip(split, keys):
        finals = ", ".join("-" if s["score"] is None else f"{s['score']:.2f}" for s in r["final"]["per_seed"])
        out.append(f"- {_esc(r['label'])}: seeds' finals {finals}"
                   + (f"; each seed's curve: ![seeds, {_esc(r['label'])}]({figures[key]})" if key in figures else ""))
    if any(key in diagnosed for key in keys):
        out += ["", "Their diagnostics seed by seed (one line per seed, in its curve's colour, the mean over seeds "
                "dashed: |A_int| / |A_ext|, f^a's agreement, the bonus paid per step and the success rate), to read "
                "whether the seeds that failed were paid another bonus than those that solved the level:", ""]
        out += [f"- {_esc(r['label'])}: ![diagnostics per seed, {_esc(r['label'])}]({diagnosed[key]})"
                for r, key in zip(split, keys) if key in diagnosed]
    return out


def length_section(rows: list[dict], final_points: int) -> list[str]:
    """Each configuration's episode length (`illm_tools.report.lengths`): the seeds' final length as IQM
    [95% CI] and mean ± std, the first and last window's mean over seeds, and the env's time limit."""
    shown = [r for r in rows if (r.get("episode_length") or {}).get("n")]
    if not shown:
        return []

    limits = {r["episode_length"].get("time_limit") for r in shown}
    limit = (f"the time limit is {limits.pop():,} steps" if len(limits) == 1 and None not in limits
             else "the time limit is in the last column")
    out = ["", f"Episode length (steps; an episode at the time limit was cut there, not ended by the agent; "
           f"{limit}): each seed's mean length of the episodes that ended in its last {final_points} curve "
           f"point{'s' * (final_points > 1)} (episode-weighted), IQM [95% CI] and mean ± std over seeds; and the "
           "mean over seeds of the first and last window:", ""]
    out += _table(["method", "episode length IQM [95% CI]", "mean ± std", "first window → last", "time limit"],
                  [[r["label"], iqm_cell(e := r["episode_length"], steps), mean_cell(e, steps),
                    f"{steps(e['first'])} → {steps(e['last'])}",
                    "-" if e.get("time_limit") is None else f"{e['time_limit']:,}"] for r in shown])
    return out


def _span(values) -> str:
    """A series' first and last window: "0.52 → 3.10"."""
    known = [v for v in values if v is not None]
    return f"{known[0]:.3g} → {known[-1]:.3g}" if known else "-"


def diagnostics_section(rows: list[dict], png: str | None) -> list[str]:
    """Per configuration with a bonus or heads: each series' first → last window, and the bonus paid
    per step before and after the level was solved (`illm_tools.report.diagnostics`)."""
    shown = [r for r in rows if r.get("diagnostics")]
    if not shown:
        return []
    from illm_tools.report.diagnostics import SOLVED, logged

    def cell(x) -> str:
        return "-" if x is None else f"{x:.3g}"

    successes = any(logged(r["diagnostics"]["success"]) for r in shown)  # none on Crafter
    out = ["", "Diagnostics over training (means over seeds, first window → last): |A_int| / |A_ext| (the bonus's "
           "share of the summed advantage), f^a's agreement with the annotator (its best action = the annotator's), "
           "the bonus paid per step as it entered the advantages"
           + (f", and that bonus in windows with success below / at least {SOLVED:g} (does it go on paying once the "
              "level is solved?):" if successes else " (the suite logs no success rate):"), ""]
    header = ["method", "|A_int| / |A_ext|", "f^a agreement", "bonus paid per step"]
    body = [[r["label"], _span(r["diagnostics"]["adv_ratio"]), _span(r["diagnostics"]["head_agreement"]),
             _span(r["diagnostics"]["bonus_paid"])] for r in shown]
    if successes:
        header += ["success", f"bonus < {SOLVED:g} / ≥ {SOLVED:g} success"]
        body = [[*line, _span(r["diagnostics"]["success"]),
                 f"{cell(r['diagnostics']['paid_unsolved'])} / {cell(r['diagnostics']['paid_solved'])}"]
                for line, r in zip(body, shown)]
    out += _table(header, body)
    if png:
        out += ["", f"![diagnostics]({png})"]
    return out


def aggregate_section(result: dict | None) -> list[str]:
    """The suite's aggregate (`illm_tools.report.aggregate`)."""
    if not result:
        return []
    n = len(result["envs"])
    out = ["## Across the levels", "",
           f"Over {n} levels ({', '.join(result['envs'])}): the IQM of the final {result['score_name']} over all runs "
           "(levels × seeds) with a stratified-bootstrap 95% interval, and the probability of improvement over "
           f"{result['baseline'] or 'ppo (not in this report)'}: P(a run of the row scores above a run of the baseline "
           "on the same level), averaged over levels, with its 95% interval (rliable). Seeds: those with a final score "
           "on every level.", ""]
    def iv(x, lo, hi) -> str:
        return "-" if x is None else f"{num(x)} [{num(lo)}, {num(hi)}]"

    out += _table(["method", f"IQM over {n} levels [95% CI]", f"P(improvement over {result['baseline'] or '-'})",
                   "seeds"],
                  [[r["label"], iv(r["iqm"], r["ci_low"], r["ci_high"]), iv(r["poi"], r["poi_low"], r["poi_high"]),
                    str(len(r["seeds"]))] for r in result["rows"]])
    return out + [""]


def _wide(results: dict) -> list[str]:
    envs, rows = results["envs"], [r for r in results["rows"]]
    labels = list(dict.fromkeys(r["label"] for r in rows))
    cells = {(r["label"], r["env_id"]): iqm_cell(r["final"]) for r in rows}
    out = ["## All envs", "", "IQM [95% CI] of the final score over seeds, one column per env (each in its suite's "
           "own score; nothing is averaged across envs):", ""]
    out += _table(["method"] + envs, [[label] + [cells.get((label, e), "-") for e in envs] for label in labels])
    return out + [""]


def _grouped(results: dict) -> list[str]:
    rows, every = results["rows"], results["settings"]["every"]
    runs = sum(len(r["runs"]) + len(r["short_runs"]) for r in rows)
    short = sum(len(r["short_runs"]) for r in rows)
    envs = results["envs"]
    out = ["## What was grouped", "",
           f"{runs} run folder{'s' * (runs != 1)} → {len(rows)} row{'s' * (len(rows) != 1)} over {len(envs)} "
           f"env{'s' * (len(envs) != 1)}" + (f", {short} left out as too short" if short else "") + ". Runs are seeds "
           "of one row only when their config.json agree on everything that changes what is learned (all but "
           "seed, folders, threads and the cache's path): runs of different envs, methods, budgets or settings "
           "are reported apart.", ""]
    if len(envs) > 1:
        counts = {e: (sum(len(r["runs"]) + len(r["short_runs"]) for r in rows if r["env_id"] == e),
                      sum(r["env_id"] == e for r in rows)) for e in envs}
        out += ["Envs: " + "; ".join(f"{e}: {n} run{'s' * (n != 1)} in {k} row{'s' * (k != 1)}"
                                     for e, (n, k) in counts.items()) + " (reported separately).", ""]
    for r in rows:
        trained = [r["trained_frames"][run] for run in r["runs"]]
        budget = ("-" if not trained else f"{trained[0]:,}" if min(trained) == max(trained)
                  else f"{min(trained):,} to {max(trained):,}")
        head = f"- {r['env_id']}, {_esc(r['label'])} ({r['score_name']}): "
        if not r["runs"]:
            out.append(head + "no run long enough for a curve point")
        else:
            out.append(head + f"seeds {', '.join(map(str, r['seeds']))}; budget: trained {budget} frames, final "
                       f"score at {_frames(r['final']['frames'])} frames; runs: "
                       + ", ".join(f"`{run}`" for run in r["runs"]))
        for run in r["final"]["no_score"]:
            out.append(f"  - `{run}`: no episode ended in its last {results['settings']['final_points']} point(s), "
                       "so it has no final score (left out of IQM and mean)")
        for run, last in r["short_runs"].items():
            out.append(f"  - `{run}` left out: trained for {last:,} frames, too short for a point at --every "
                       f"{every:,} (a run gives a last, shorter window once it passes half of it)")
    return out + [""]


def quality_markdown(result: dict) -> list[str]:
    """The quality section of report.md."""
    if not result["points"]:
        return []
    out = ["## Annotator quality", "",
           "Final score against the annotator's agreement with minigrid's BabyAI bot (`illm probe`, the run's "
           "action calibration): each row's probe is the one of its env, backend, model, history and layout. "
           "Methods on other states' targets or on none are references.", ""]
    rows = [[p["env_id"], p["label"], f"{p['agreement']:.3f}", iqm_cell(p["final"])] for p in result["points"]]
    rows += [[line["env_id"], line["label"], "-", iqm_cell(line["final"])] for line in result["lines"]]
    rows += [[m["env_id"], f"{m['model']} ({m['backend']}), probed only", f"{m['agreement']:.3f}", "-"]
             for m in result["markers"]]
    out += _table(["env", "configuration", "probe agreement", "final IQM [95% CI]"], rows)
    return out + ["", "![final score against annotator quality](quality.png)", ""]


def _provenance(settings: dict, rows: list[dict]) -> list[str]:
    """Which code wrote the report and trained its runs; says when runs predate the report's commit."""
    code = settings.get("code")
    if not code:  # a report written before provenance was recorded
        return []
    commit = code.get("commit")
    head = f"Written by `{settings.get('command', 'illm report')}` at " + \
        (f"commit {commit[:12]}{' with uncommitted changes' if code.get('dirty') else ''}" if commit
         else f"illm {code.get('version')} (no git commit)")
    entries = {run: e for r in rows for run, e in (r.get("provenance") or {}).items()}
    unknown = sorted(run for run, e in entries.items() if not e)
    older: dict[str, list[str]] = {}
    for run, e in entries.items():
        for c in provenance.predating([x.get("commit") for x in e], commit):
            older.setdefault(c, []).append(run)
    said = [f"{head}."]
    if older:
        parts = ", ".join(f"{c[:12]} ({len(runs)} run{'s' * (len(runs) != 1)})" for c, runs in sorted(older.items()))
        said.append(f"**Runs predate the current code**: trained (in part) by {parts}; each run's "
                    "provenance.json and results.json name the commands.")
    elif entries and len(unknown) < len(entries):
        said.append("Every run with a provenance was trained at this commit.")
    if unknown:
        said.append(f"{len(unknown)} run{'s' * (len(unknown) != 1)} recorded no provenance (trained before illm "
                    "recorded it): their code is unknown.")
    return [" ".join(said), ""]


def render(results: dict) -> str:
    settings, rows = results["settings"], results["rows"]
    runs, short = sum(len(r["runs"]) for r in rows), sum(len(r["short_runs"]) for r in rows)
    lines = ["# Training report", "",
             f"{runs} run{'s' * (runs != 1)}" + (f" (and {short} too short, left out)" if short else "")
             + f", {len(rows)} configuration{'s' * (len(rows) != 1)}, {len(results['envs'])} "
             f"env{'s' * (len(results['envs']) != 1)}. Curve points: the suite's score over windows of "
             f"{settings['every']:,} frames. Numbers: results.json; figures: PNG files beside this one.", ""]
    lines += _provenance(settings, rows)
    for env in results["envs"]:
        lines += _env_section(env, [r for r in rows if r["env_id"] == env],
                              {**settings, "seed_figures": results["files"].get("seeds", {}),
                               "seed_diagnostics_figures": results["files"].get("seeds_diagnostics", {})},
                              results["files"]["curves"].get(env), results["files"].get("diagnostics", {}).get(env))
    if len(results["envs"]) > 1:
        lines += _wide(results)
    lines += aggregate_section(results.get("aggregate"))
    if results["files"]["final"]:
        lines += [f"Final scores with their intervals: ![final scores]({results['files']['final']})", ""]
    if results.get("quality"):
        lines += quality_markdown(results["quality"])
    lines += _grouped(results)
    return "\n".join(lines)
