"""Crafter in a report: each achievement's success rate, and the score of a window's episodes taken together.

A run on a suite with achievements (Crafter) logs, per update, each achievement's success rate over the
episodes that ended in that update (metrics.jsonl: `charts/achievement_NAME` beside `charts/episodes`). A
curve window's rate is the episode-weighted mean of its updates' rates, which is exactly the share of the
window's episodes that unlocked the achievement; the window's Crafter score is Hafner (2021)'s formula on
those pooled rates (`crafter_text.crafter_score`), the score of the window's episodes as the paper computes
it over a run's episodes, not a mean of per-update scores (a geometric mean of rates does not average).

A row's final achievements: each seed's rates pooled over the episodes of its last `final_points` windows
(the windows its final score reads), then per achievement the mean over seeds, with each seed's rate beside
it. The published 1M-step figures are the Crafter paper's, quoted as such where a page cites them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from illm_tools.report.stats import in_window

PREFIX = "charts/achievement_"


def read_updates(run_dir: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]] | None:
    """(global steps, episodes, {achievement: rate}) of a run's updates from its metrics.jsonl; None where
    the run logs no achievements (not a Crafter run, or no metrics.jsonl). An update in which no episode
    ended logs no rates: its rates are 0 at weight 0."""
    path = Path(run_dir) / "metrics.jsonl"
    if not path.is_file():
        return None
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    names = sorted({k[len(PREFIX):] for row in rows for k in row if k.startswith(PREFIX)})
    if not names:
        return None
    rows = {int(row["global_step"]): row for row in rows if "global_step" in row}  # a resumed run's last word
    steps = np.array(sorted(rows), dtype=np.int64)
    episodes = np.array([float(rows[s].get("charts/episodes") or 0) for s in steps])
    rates = {n: np.array([float(rows[s].get(PREFIX + n) or 0.0) for s in steps]) for n in names}
    return steps, episodes, rates


def pooled(updates, windows: list[np.ndarray]) -> dict[str, float] | None:
    """Each achievement's rate over the episodes of the updates `windows` select (boolean masks over the
    updates, or'ed together); None where no episode ended in them."""
    steps, episodes, rates = updates
    mask = np.zeros(len(steps), dtype=bool)
    for window in windows:
        mask |= window
    n = episodes[mask].sum()
    if not n:
        return None
    return {name: float((r[mask] * episodes[mask]).sum() / n) for name, r in rates.items()}


def score(rates: dict[str, float]) -> float:
    """The Crafter score (percent) of pooled rates (fractions)."""
    from illm_tools.envs.crafter_text import ACHIEVEMENTS, crafter_score

    return crafter_score({name: 100.0 * rates.get(name, 0.0) for name in ACHIEVEMENTS})


def window_scores(run_dir: Path, ends: list[int], every: int) -> list[float] | None:
    """Per curve point (window ending at each of `ends`), the Crafter score of its episodes pooled (NaN where
    none ended); None where the run logs no achievements."""

    updates = read_updates(run_dir)
    if updates is None:
        return None
    out = []
    for end in ends:
        rates = pooled(updates, [in_window(updates[0], end, every)])
        out.append(score(rates) if rates is not None else float("nan"))
    return out


def final_achievements(runs: list[str], seeds: list[int], frames: list[int], every: int,
                       final_points: int) -> dict | None:
    """A row's achievements: {"points": the final windows' ends, "per_seed": [{"seed", "run", "rates"}],
    "mean": {achievement: mean over seeds}}; None where no run logs achievements."""

    used = frames[-final_points:]
    per_seed = []
    for run, seed in zip(runs, seeds):
        updates = read_updates(Path(run))
        if updates is None:
            continue
        rates = pooled(updates, [in_window(updates[0], end, every) for end in used])
        if rates is not None:
            per_seed.append({"seed": seed, "run": run, "rates": rates})
    if not per_seed:
        return None
    names = sorted({n for s in per_seed for n in s["rates"]})
    mean = {n: float(np.mean([s["rates"].get(n, 0.0) for s in per_seed])) for n in names}
    return {"points": used, "per_seed": per_seed, "mean": mean}


def achievements_section(rows: list[dict]) -> list[str]:
    """report.md's table for an env whose rows carry achievements: one line per achievement, one column per
    configuration, the mean over seeds of each seed's success rate in its final windows, in percent."""
    rows = [r for r in rows if r.get("achievements")]
    if not rows:
        return []
    names = sorted({n for r in rows for n in r["achievements"]["mean"]})
    seeds = ", ".join(f"{r['label']} {len(r['achievements']['per_seed'])}" for r in rows)
    lines = ["Success rate of each achievement (%): the share of the episodes that ended in each seed's final "
             f"windows that unlocked it, mean over seeds (seeds: {seeds}); each seed's rates are in results.json.",
             "", "| achievement | " + " | ".join(r["label"] for r in rows) + " |",
             "|---|" + "---|" * len(rows)]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(f"{100 * r['achievements']['mean'].get(name, 0.0):.1f}"
                                                for r in rows) + " |")
    return lines + [""]
