"""PNG figures of a report (matplotlib, Agg backend): learning curves with bootstrap bands, final
scores with their intervals, and per-configuration visitation heatmaps summed over seeds."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> Path:
    """Lay the figure out, save it with every label inside the image, and close it. matplotlib's
    notice that a layout could not fit (long labels) is not shown: the saved image's bounds are
    fitted to its contents instead (what a user reads is illm's output)."""
    import warnings

    plt = _pyplot()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Tight layout not applied", category=UserWarning)
        fig.tight_layout()
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    return Path(path)


def _nan(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def colours(labels: list[str]) -> dict[str, tuple]:
    """One colour per line label, the same in every figure of a report (seaborn's colorblind
    palette, as rliable's figures use)."""
    import seaborn as sns

    palette = sns.color_palette("colorblind", n_colors=max(len(labels), 1))
    return {label: tuple(palette[i % len(palette)]) for i, label in enumerate(labels)}


def panels(rows: list[dict]) -> tuple[list[str], list[tuple[str, str]]]:
    """The small multiples of an env's rows: the settings two or more methods vary in (a paper
    table's columns: Table 1's distractor counts) make the panels, and each row is drawn in its
    panel as a line named by its method and its other settings. Returns (panel keys, per row
    (panel title, line label))."""
    by_key: dict[str, set[str]] = {}
    for row in rows:
        for key in row.get("settings", {}):
            by_key.setdefault(key, set()).add(row["method"])
    keys = sorted(k for k, methods in by_key.items() if len(methods) > 1)
    out = []
    for row in rows:
        settings = row.get("settings", {})
        title = ", ".join(f"{k} {settings[k]}" for k in keys if k in settings)
        rest = [f"{k} {v}" for k, v in settings.items() if k not in keys]
        if not keys and "label" in row:  # no panels: the row's own label (an experiment's grid label, `group_labels`)
            out.append((title, row["label"]))
        else:
            out.append((title, row["method"] + (f" ({', '.join(rest)})" if rest else "")))
    return keys, out


def setting_order(value) -> tuple:
    """Sort key of a setting's value: numbers by value (4 before 16), then text."""
    try:
        return (0, float(value), "")
    except (TypeError, ValueError):
        return (1, 0.0, str(value))


def panel_titles(rows: list[dict]) -> list[str]:
    """The panels' titles (`panels`) in the order of their settings' values, numbers by value."""
    keys, placed = panels(rows)

    def key(row: dict) -> tuple:
        settings = row.get("settings", {})
        return tuple(setting_order(settings.get(k)) for k in keys)

    first = {}
    for row, (title, _) in sorted(zip(rows, placed), key=lambda pair: key(pair[0])):
        first.setdefault(title, row)
    return list(first)


def curves_png(env_id: str, score_name: str, rows: list[dict], path: Path, colour: dict[str, tuple] | None = None) -> Path:
    """One env's learning curves, one panel per setting that several methods share (small multiples,
    `panels`), one colour per line across panels: each row's ({"label", "method", "settings",
    "frames", "mean", "band_low", "band_high"}) mean over seeds against frames, shaded between the
    band's ends where it has one."""
    plt = _pyplot()
    _, placed = panels(rows)
    titles = panel_titles(rows)
    lines = list(dict.fromkeys(line for _, line in placed))
    colour = {**colours(lines), **(colour or {})}
    fig, axes = plt.subplots(1, len(titles), figsize=(4.6 * len(titles) + 1.8, 3.8), dpi=100, squeeze=False,
                             sharey=True)
    banded = False
    for ax, title in zip(axes[0], titles):
        for row, (where, line) in zip(rows, placed):
            if where != title:
                continue
            frames, mean = np.array(row["frames"], dtype=float), _nan(row["mean"])
            ax.plot(frames, mean, marker="o" if len(frames) < 3 else None, markersize=3, color=colour[line],
                    label=f"{line} ({len(row['seeds'])} seed{'s' * (len(row['seeds']) != 1)})")
            low, high = _nan(row["band_low"]), _nan(row["band_high"])
            if np.isfinite(low).any():
                ax.fill_between(frames, low, high, color=colour[line], alpha=0.2, linewidth=0)
                banded = True
        if score_name == "success rate":  # the whole range: an autoscaled axis makes a gap of 0.007 a cliff
            ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("frames")
        ax.set_title(title or env_id, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"{score_name} (mean over seeds{', 95% bootstrap band' if banded else '; one seed: no band'})",
                          fontsize=8)
    handles = {}
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab.rsplit(" (", 1)[0] if lab.endswith("seeds)") or lab.endswith("seed)") else lab, h)
    fig.legend(list(handles.values()), list(handles), loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=7,
               frameon=False)
    if len(titles) > 1 or titles[0]:
        fig.suptitle(env_id, fontsize=10)
    return save_figure(fig, path)


def seeds_png(row: dict, path: Path) -> Path:
    """One configuration's seeds as separate curves (its `final["seed_curves"]`: each seed's points
    against the row's frames), drawn where its seeds split (`stats.seeds_split`)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.8), dpi=100)
    frames = np.array(row["frames"], dtype=float)
    for seed in row["final"]["seed_curves"]:
        ax.plot(frames, _nan(seed["points"]), marker="o" if len(frames) < 3 else None, markersize=3,
                label=f"seed {seed['seed']}")
    ax.plot(frames, _nan(row["mean"]), color="black", linestyle="--", linewidth=1, label="mean over seeds")
    if row["score_name"] == "success rate":
        ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("frames")
    ax.set_ylabel(f"{row['score_name']}, one line per seed", fontsize=8)
    ax.set_title(f"{row['env_id']}: {row['label']}, seeds that split", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=7, frameon=False)
    return save_figure(fig, path)


FINAL_PANELS_PER_ROW = 3
"""Panels of final.png side by side before it wraps to the next row."""


def final_png(panels_: list[dict], path: Path, colour: dict[str, tuple] | None = None) -> Path:
    """Final scores drawn as rliable draws interval estimates (`plot_interval_estimates`): per env a
    panel, per configuration a bar spanning its 95% interval with a black tick at its IQM, each
    configuration in its colour of the report's curves; configurations without a score in an env
    are left out of its panel."""
    plt = _pyplot()
    shown = [p for p in panels_ if any(r["final"]["iqm"] is not None for r in p["rows"])]
    lines = {}  # a row's line label (`panels`): its colour in the curves
    for panel in shown:
        lines.update({row["label"]: line for row, (_, line) in zip(panel["rows"], panels(panel["rows"])[1])})
    colour = {**colours(list(dict.fromkeys(lines.values()))), **(colour or {})}
    height = max(2.0, 0.42 * max(len(p["rows"]) for p in shown) + 1.1)
    across = min(len(shown), FINAL_PANELS_PER_ROW)  # a suite of levels wraps into rows, not one long strip
    down = -(-len(shown) // across)
    fig, axes = plt.subplots(down, across, figsize=(4.6 * across, height * down), dpi=100, squeeze=False)
    for ax in axes.ravel()[len(shown):]:
        ax.set_visible(False)
    for ax, panel in zip(axes.ravel(), shown):
        titles = panel_titles(panel["rows"])
        placed = dict(zip((r["label"] for r in panel["rows"]), (t for t, _ in panels(panel["rows"])[1])))
        rows = sorted((r for r in panel["rows"] if r["final"]["iqm"] is not None),
                      key=lambda r: titles.index(placed[r["label"]]))  # grouped as the curves' panels
        for y, row in enumerate(rows):
            final = row["final"]
            low = final["ci_low"] if final["ci_low"] is not None else final["iqm"]
            high = final["ci_high"] if final["ci_high"] is not None else final["iqm"]
            ax.barh(y, max(high - low, 1e-3), left=low, height=0.6, color=colour.get(lines[row["label"]], "C0"),
                    alpha=0.75)
            ax.vlines(final["iqm"], y - 0.28, y + 0.28, color="black", alpha=0.6)
        ax.set_yticks(range(len(rows)), [r["label"] for r in rows], fontsize=8)
        ax.set_ylim(-0.6, len(rows) - 0.4)
        ax.invert_yaxis()
        if panel["score_name"] in ("success rate",):
            ax.set_xlim(-0.02, 1.02)
        ax.set_xlabel(f"final {panel['score_name']}: IQM (tick), 95% CI (bar)", fontsize=8)
        ax.set_title(panel["env_id"], fontsize=9)
        ax.grid(axis="x", alpha=0.3)
        for side in ("top", "right", "left"):
            ax.spines[side].set_visible(False)
    return save_figure(fig, path)


def summed_counts(grids: list[np.ndarray]) -> np.ndarray:
    """Visit-count grids of several seeds added cell by cell (grids grow with the cells a run
    reached, so smaller ones are padded with zeros at the bottom and right)."""
    grids = [np.asarray(g, dtype=np.int64) for g in grids]
    shape = (max(g.shape[0] for g in grids), max(g.shape[1] for g in grids))
    total = np.zeros(shape, np.int64)
    for g in grids:
        total[:g.shape[0], :g.shape[1]] += g
    return total


def visitation_png(grids: list[np.ndarray], path: Path, title: str) -> Path:
    """A heatmap of the seeds' visit counts summed (`illm_tools.rl.visitation.heatmap_png`)."""
    from illm_tools.rl.visitation import heatmap_png

    return heatmap_png(summed_counts(grids), path, title)


def bonus_png(visits: list[np.ndarray], paid: list[np.ndarray], path: Path, title: str) -> Path:
    """Where the bonus was paid: the seeds' bonus summed per cell over their visits summed (the bonus
    paid per visit of a cell; cells never visited in grey: magma's top colour is near white, so blank
    cells would read as the highest bonus), linear colours from 0 (or the lowest
    value, where a bonus is negative): a scale fitted to the cells' own range would paint a nearly even
    bonus (0.0030 to 0.0032) as black against white."""
    plt = _pyplot()
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    count = summed_counts(visits).astype(float)
    total = np.zeros(count.shape)
    for grid in paid:
        grid = np.asarray(grid, dtype=float)[:count.shape[0], :count.shape[1]]
        total[:grid.shape[0], :grid.shape[1]] += grid
    per_visit = np.ma.masked_where(count <= 0, total / np.maximum(count, 1))
    h, w = count.shape if count.size else (1, 1)
    fig, ax = plt.subplots(figsize=(4.5, min(6.0, max(1.8, 3.6 * h / max(w, 1) + 0.9))), dpi=100)
    low = min(0.0, float(per_visit.min())) if per_visit.count() else 0.0
    cmap = plt.get_cmap("magma").with_extremes(bad="#bdbdbd")
    image = ax.imshow(per_visit, cmap=cmap, interpolation="nearest", vmin=low)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f"{title}\n(grey: never visited)", fontsize=9)
    fig.colorbar(image, cax=make_axes_locatable(ax).append_axes("right", size="4%", pad=0.08), label="bonus per visit")
    return save_figure(fig, path)
