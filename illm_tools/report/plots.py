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


def _nan(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def curves_png(env_id: str, score_name: str, rows: list[dict], path: Path) -> Path:
    """One env's learning curves: per row ({"label", "frames", "mean", "band_low", "band_high"}) its
    mean over seeds against frames, shaded between the band's ends where it has one."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=100)
    for row in rows:
        frames, mean = np.array(row["frames"], dtype=float), _nan(row["mean"])
        (line,) = ax.plot(frames, mean, marker="o" if len(frames) < 3 else None, markersize=3,
                          label=f"{row['label']} ({len(row['seeds'])} seed{'s' * (len(row['seeds']) != 1)})")
        low, high = _nan(row["band_low"]), _nan(row["band_high"])
        if np.isfinite(low).any():
            ax.fill_between(frames, low, high, color=line.get_color(), alpha=0.2, linewidth=0)
    ax.set_xlabel("frames")
    ax.set_ylabel(score_name)
    ax.set_title(f"{env_id}: mean over seeds, 95% bootstrap band", fontsize=9)
    ax.grid(alpha=0.3)
    if rows:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def final_png(panels: list[dict], path: Path) -> Path:
    """Final scores, one panel per env ({"env_id", "score_name", "rows": [{"label", "final"}]}):
    each row's IQM as a dot with its 95% interval as a bar."""
    plt = _pyplot()
    height = max(2.0, 0.45 * max(len(p["rows"]) for p in panels) + 1.2)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), height), dpi=100, squeeze=False)
    for ax, panel in zip(axes[0], panels):
        rows = [r for r in panel["rows"] if r["final"]["iqm"] is not None]
        for y, row in enumerate(rows):
            final = row["final"]
            if final["ci_low"] is not None:
                ax.plot([final["ci_low"], final["ci_high"]], [y, y], linewidth=5, alpha=0.4, color=f"C{y % 10}")
            ax.plot([final["iqm"]], [y], "o", color=f"C{y % 10}")
        ax.set_yticks(range(len(rows)), [r["label"] for r in rows], fontsize=7)
        ax.set_ylim(-0.7, len(rows) - 0.3)
        ax.invert_yaxis()
        ax.set_xlabel(f"final {panel['score_name']} (IQM, 95% CI)", fontsize=8)
        ax.set_title(panel["env_id"], fontsize=9)
        ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


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
