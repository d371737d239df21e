"""Across levels: one number per configuration over a suite of levels, as rliable reports Atari.

For rows with the same label in every env of a report whose envs share a score (success rate):
- the IQM over all runs (levels x seeds, rliable's `aggregate_iqm` of the [seeds, levels] matrix)
  with a stratified-bootstrap 95% interval (resampled within each level);
- the probability of improvement over a baseline row (ppo): P(X > Y) averaged over levels, each
  level's the Mann-Whitney statistic of the two rows' seeds (rliable's
  `probability_of_improvement`), with its stratified-bootstrap interval.
A configuration enters with the seeds that have a final score on every level (its matrix needs one
row per seed); the seed count is stated beside each number.
"""

from __future__ import annotations

import numpy as np

from illm_tools.report.stats import CONFIDENCE, _quiet, seeded

BASELINE = "ppo"


def _matrix(rows: list[dict], envs: list[str]) -> tuple[np.ndarray, list[int]]:
    """[seeds, levels] final scores of one label's rows, over the seeds scored on every level."""
    per_env = {r["env_id"]: {s["seed"]: s["score"] for s in r["final"]["per_seed"]} for r in rows}
    seeds = sorted(set.intersection(*(
        {seed for seed, score in per_env[e].items() if score is not None and not np.isnan(score)} for e in envs)))
    return np.array([[per_env[e][s] for e in envs] for s in seeds], dtype=float).reshape(len(seeds), len(envs)), seeds


def aggregate(rows: list[dict], envs: list[str], reps: int, seed: int, baseline: str = BASELINE) -> dict | None:
    """{"envs", "score_name", "baseline", "rows": [{"label", "seeds", "iqm", "ci_low", "ci_high",
    "poi", "poi_low", "poi_high"}]}; None with fewer than two envs or envs of different scores."""
    from rliable import library, metrics

    if len(envs) < 2 or len({r["score_name"] for r in rows}) != 1:
        return None
    labels = [label for label in dict.fromkeys(r["label"] for r in rows)
              if {r["env_id"] for r in rows if r["label"] == label} >= set(envs)]
    matrices = {}
    for label in labels:
        matrix, seeds = _matrix([r for r in rows if r["label"] == label], envs)
        if len(seeds) >= 2:
            matrices[label] = (matrix, seeds)
    if not matrices:
        return None

    def iqm(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x)])

    out = []
    with seeded(seed), _quiet():
        points, intervals = library.get_interval_estimates({k: m for k, (m, _) in matrices.items()}, iqm, reps=reps,
                                                           confidence_interval_size=CONFIDENCE)
    for label, (matrix, seeds) in matrices.items():
        entry = {"label": label, "seeds": seeds, "iqm": float(points[label][0]),
                 "ci_low": float(intervals[label][0, 0]), "ci_high": float(intervals[label][1, 0]),
                 "poi": None, "poi_low": None, "poi_high": None}
        if baseline in matrices and label != baseline:
            with seeded(seed), _quiet():
                pair = {"x": (matrix, matrices[baseline][0])}
                p, ci = library.get_interval_estimates(pair, metrics.probability_of_improvement, reps=reps,
                                                       confidence_interval_size=CONFIDENCE)
            entry.update(poi=float(np.ravel(p["x"])[0]), poi_low=float(np.ravel(ci["x"][0])[0]),
                         poi_high=float(np.ravel(ci["x"][1])[0]))
        out.append(entry)
    return {"envs": list(envs), "score_name": rows[0]["score_name"], "baseline": baseline if baseline in matrices
            else None, "rows": out}
