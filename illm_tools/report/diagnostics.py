"""Why a bonus helps or hurts, read from a run's metrics.jsonl (issue 28): per configuration and
over training, the ratio of the intrinsic to the extrinsic advantage, f^a's agreement with the
annotator, the bonus paid per step (as it entered the advantages: normalised reward x its weight),
and the success rate beside them, so a bonus that goes on paying after the level is solved shows.

Each series is windowed as the learning curves are (the mean of the updates whose frame falls in
(F - every, F]), then averaged over seeds (NaN where no seed logged it). `diagnostics_png` draws one
panel per series; the report's table gives each series' first and last window and the bonus paid
per step in the windows where the success rate was at least `SOLVED`. For a configuration whose seeds
split (`stats.seeds_split`), each seed's series are kept too and `seeds_diagnostics_png` draws them one
line per seed: the mean over seeds would hide whether the seeds that failed were paid another bonus.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from illm_tools.report.stats import in_window

SERIES = {  # name -> (metrics.jsonl column(s), axis label)
    "success": ("charts/success_rate", "success rate"),
    "adv_ratio": ("charts/adv_int_ext_ratio", "|A_int| / |A_ext|"),
    "head_agreement": ("charts/head_agreement", "f^a agrees with the annotator"),
    "bonus_paid": (("charts/intrinsic_reward", "charts/bonus_weight"), "bonus paid per step"),
}
SOLVED = 0.8
"""A window counts as solved from this success rate on."""


def logged(values) -> bool:
    """Whether a series holds a value in any window (None, as results.json writes it, and NaN are
    windows without one; a suite without a success rate, Crafter, has none in its success series)."""
    return any(v is not None and np.isfinite(v) for v in values)


def _value(row: dict, column) -> float:
    if isinstance(column, tuple):  # a product (the normalised reward x its weight)
        values = [row.get(c) for c in column]
        return float(np.prod(values)) if all(v is not None for v in values) else np.nan
    value = row.get(column)
    return np.nan if value is None else float(value)


def run_series(run_dir: Path, frames: list[int], every: int) -> dict[str, list[float]]:
    """Each series of one run at the curve's `frames` (window ends)."""
    path = Path(run_dir) / "metrics.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
    steps = np.array([int(r.get("global_step", 0)) for r in rows])
    out = {}
    for name, (column, _) in SERIES.items():
        values = np.array([_value(r, column) for r in rows], dtype=float)
        points = []
        for end in frames:
            window = values[in_window(steps, end, every)]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                points.append(float(np.nanmean(window)) if window.size else np.nan)
        out[name] = points
    return out


def row_diagnostics(row: dict, every: int) -> dict | None:
    """The seeds' mean of each series for a report row (None when no series was logged)."""
    if not row["runs"] or not row["frames"]:
        return None
    per_run = [run_series(Path(run), row["frames"], every) for run in row["runs"]]
    out = {"frames": list(row["frames"])}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for name in SERIES:
            out[name] = np.nanmean(np.array([r[name] for r in per_run], dtype=float), axis=0).tolist()
    if all(np.all(np.isnan(out[n])) for n in ("head_agreement", "bonus_paid")):  # no bonus, no heads (ppo)
        return None
    if row["final"].get("split"):  # drawn seed by seed (`seeds_diagnostics_png`), as its curves are
        out["per_seed"] = [{"seed": s["seed"], **series} for s, series in zip(row["final"]["per_seed"], per_run)]
    success = np.array(out["success"], dtype=float)  # NaN: a window without episodes, or a suite without
    solved, unsolved = success >= SOLVED, success < SOLVED  # a success rate (Crafter): neither
    paid = np.array(out["bonus_paid"], dtype=float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out["paid_solved"] = float(np.nanmean(paid[solved])) if solved.any() else None
        out["paid_unsolved"] = float(np.nanmean(paid[unsolved])) if unsolved.any() else None
    return out


def diagnostics_png(env_id: str, rows: list[dict], path: Path, colour: dict[str, tuple]) -> Path:
    """One panel per series, a line per row with diagnostics (its label's colour)."""
    return _panels([(row["label"], row["diagnostics"], {"color": colour.get(row["label"])}) for row in rows],
                   env_id, path)


def seeds_diagnostics_png(row: dict, path: Path) -> Path:
    """One panel per series of a configuration whose seeds split, a line per seed (its `per_seed`
    series, in the colours of its seeds' curves, `plots.seeds_png`) and the mean over seeds dashed."""
    d = row["diagnostics"]
    seeds = [(f"seed {s['seed']}", {**s, "frames": d["frames"]}, {}) for s in d["per_seed"]]
    mean = ("mean over seeds", d, {"color": "black", "linestyle": "--", "linewidth": 1})
    return _panels(seeds + [mean], f"{row['env_id']}: {row['label']}, seeds that split, one line per seed", path)


def _panels(lines: list[tuple[str, dict, dict]], title: str, path: Path) -> Path:
    """One panel per series a line has values of (a suite without a success rate, Crafter, has no success
    panel), a line per (label, diagnostics with their frames, matplotlib's line style)."""
    from matplotlib.ticker import MaxNLocator

    from illm_tools.report.plots import _pyplot, save_figure

    plt = _pyplot()
    names = [n for n in SERIES if any(logged(d[n]) for _, d, _ in lines)]
    names = names or ["success"]  # nothing logged: one empty panel, not a figure without axes
    fig, axes = plt.subplots(1, len(names), figsize=(4.0 * len(names), 3.4), dpi=100, squeeze=False)
    axes = axes[0]
    for ax, name in zip(axes, names):
        for label, d, style in lines:
            values = [np.nan if v is None or (name == "adv_ratio" and v <= 0) else v for v in d[name]]
            ax.plot(d["frames"], values, label=label, **style)
        ax.set_title(SERIES[name][1], fontsize=9)
        ax.set_xlabel("frames")
        ax.xaxis.set_major_locator(MaxNLocator(4))  # four panels abreast: six-digit ticks would run together
        if name == "adv_ratio":
            ax.set_yscale("log")
            ax.axhline(1.0, color="grey", lw=0.8, ls=":")
        if name == "success":
            ax.axhline(SOLVED, color="grey", lw=0.8, ls=":")
    axes[-1].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
