"""Per-cell visit counts of a training run (paper Figure 1's heatmaps), for envs that report the
agent's position (MiniGrid/BabyAI: `info["agent_pos"]`), and where its bonus was paid.

`VisitCounts` adds the positions of every step's new states into an int64 grid indexed [y, x],
growing as needed; the trainer saves it as `visitation.npy` in the run folder with each checkpoint
(and keeps it in the checkpoint, so a resumed run goes on counting). With `weighted=True` it sums
a weight per position instead (float64): the intrinsic reward paid at each cell, saved as
`bonus_visitation.npy` (`BONUS_FILE`), so bonus / visits is the bonus paid per visit of a cell.
`heatmap_png` draws a grid (log-scaled colours, cells never visited left blank) with matplotlib's
Agg backend.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

FILE = "visitation.npy"
BONUS_FILE = "bonus_visitation.npy"


class VisitCounts:
    def __init__(self, counts: np.ndarray | None = None, *, weighted: bool = False):
        self.dtype = np.float64 if weighted else np.int64
        self._counts = np.zeros((0, 0), self.dtype) if counts is None else np.asarray(counts, self.dtype).copy()

    @property
    def counts(self) -> np.ndarray:
        """int64 [H, W]: visits per cell (row y, column x)."""
        return self._counts

    def add(self, positions: np.ndarray, weights: np.ndarray | None = None) -> None:
        """Count int [N, 2] (x, y) positions (or, weighted, add `weights` [N] at them); rows with a
        negative x (no position) are skipped."""
        positions = np.asarray(positions, dtype=np.int64).reshape(-1, 2)
        weights = np.ones(len(positions)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
        keep = positions[:, 0] >= 0
        positions, weights = positions[keep], weights[keep]
        if not len(positions):
            return
        need = (int(positions[:, 1].max()) + 1, int(positions[:, 0].max()) + 1)
        if need[0] > self._counts.shape[0] or need[1] > self._counts.shape[1]:
            grown = np.zeros((max(need[0], self._counts.shape[0]), max(need[1], self._counts.shape[1])), self.dtype)
            grown[:self._counts.shape[0], :self._counts.shape[1]] = self._counts
            self._counts = grown
        np.add.at(self._counts, (positions[:, 1], positions[:, 0]), weights.astype(self.dtype))

    def save(self, run_dir: str | os.PathLike, name: str = FILE) -> Path:
        """Write run_dir/`name` (visitation.npy) atomically."""
        from illm_tools import durable

        path = Path(run_dir) / name
        with durable.staged(path) as fh:
            np.save(fh, self._counts)
        return durable.commit(fh.name, path)

    @classmethod
    def load(cls, run_dir: str | os.PathLike, name: str = FILE) -> VisitCounts:
        path = Path(run_dir) / name
        weighted = name == BONUS_FILE
        return cls(np.load(path), weighted=weighted) if path.is_file() else cls(weighted=weighted)

    def state_dict(self) -> dict:
        """For checkpoint.pt (a tensor: checkpoints load with torch's weights_only, which refuses numpy)."""
        import torch

        return {"counts": torch.as_tensor(self._counts.copy())}

    def load_state_dict(self, state: dict) -> None:
        counts = state["counts"]
        self._counts = np.array(counts.numpy() if hasattr(counts, "numpy") else counts, dtype=self.dtype)


def heatmap_png(counts: np.ndarray, path: str | os.PathLike, title: str = "") -> Path:
    """A PNG heatmap of a visit-count grid: log-scaled colours, unvisited cells blank, a colour bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    counts = np.asarray(counts, dtype=float)
    masked = np.ma.masked_less_equal(counts, 0)
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    h, w = counts.shape if counts.size else (1, 1)
    fig, ax = plt.subplots(figsize=(4.5, min(6.0, max(1.8, 3.6 * h / max(w, 1) + 0.9))), dpi=100)
    image = ax.imshow(masked, cmap="viridis", norm=LogNorm(vmin=1, vmax=max(float(counts.max()), 1.0)),
                      interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=9)
    # the colour bar as tall as the grid (a wide, flat grid no longer sits beside a bar twice its height)
    fig.colorbar(image, cax=make_axes_locatable(ax).append_axes("right", size="4%", pad=0.08), label="visits")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
