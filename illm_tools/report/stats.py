"""Statistics over seeds with rliable: the interquartile mean of final scores with a stratified-
bootstrap 95% confidence interval, and pointwise bootstrap bands of learning curves.

rliable's IQM is `scipy.stats.trim_mean(scores, 0.25)`, which cuts int(0.25 * n) scores from each
end: with 2 or 3 seeds it cuts nothing (the IQM is the mean), with 4 it keeps the middle 2. Its
percentile bootstrap of 3 seeds gives [min, max] as the 95% interval (each end has a 1/27 chance of
a resample made of it alone, above 2.5%). rliable draws its resamples from numpy's global random
state (its `random_state` argument is not used by the stratified bootstrap), so `seeded` fixes that
state for the call and puts the caller's back afterwards.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

import numpy as np

CONFIDENCE = 0.95


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """numpy's global random state set to `seed` inside, restored after."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(saved)


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """arch's deprecation notices and the all-NaN warnings of windows where no episode ended."""
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", FutureWarning)
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def final_scores(table: np.ndarray, points: int) -> np.ndarray:
    """Each seed's final score: the mean of its last `points` curve points (NaN points, windows in
    which no episode ended, left out; a seed with none is NaN). `table` is [seeds, points]."""
    table = np.asarray(table, dtype=float)
    if table.ndim != 2 or not table.shape[1]:
        return np.full(len(table), np.nan)
    with _quiet():
        return np.nanmean(table[:, -points:], axis=1)


def iqm_interval(scores, reps: int = 2000, seed: int = 0) -> dict:
    """{"n", "iqm", "ci_low", "ci_high", "mean", "std"} of one configuration's per-seed scores
    (NaN scores left out): rliable's IQM with its stratified-bootstrap percentile interval (None
    with fewer than 2 seeds), and the plain mean ± std (population std, as the curves' table)."""
    from rliable import library, metrics

    scores = np.asarray(scores, dtype=float).ravel()
    scores = scores[~np.isnan(scores)]
    n = len(scores)
    out = {"n": n, "iqm": None, "ci_low": None, "ci_high": None, "mean": None, "std": None}
    if not n:
        return out
    out["mean"], out["std"] = float(scores.mean()), float(scores.std())
    if n < 2:
        out["iqm"] = float(metrics.aggregate_iqm(scores[:, None]))
        return out

    def iqm(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x)])

    with seeded(seed), _quiet():
        point, interval = library.get_interval_estimates({"x": scores[:, None]}, iqm, reps=reps,
                                                         confidence_interval_size=CONFIDENCE)
    out["iqm"] = float(point["x"][0])
    out["ci_low"], out["ci_high"] = (float(v) for v in interval["x"][:, 0])
    return out


def curve_band(table, reps: int = 2000, seed: int = 0) -> tuple[list, list, list]:
    """Mean curve over seeds with a pointwise stratified-bootstrap 95% band (rliable; every frame's
    seeds resampled): ([mean], [low], [high]) per point; the band is None with fewer than 2 seeds."""
    from rliable import library

    table = np.asarray(table, dtype=float)
    with _quiet():
        mean = np.nanmean(table, axis=0) if len(table) else np.zeros(table.shape[1:])
    if len(table) < 2 or not table.shape[1]:
        return mean.tolist(), [None] * len(mean), [None] * len(mean)

    def nanmean(x: np.ndarray) -> np.ndarray:
        return np.nanmean(x, axis=0)

    with seeded(seed), _quiet():
        _, interval = library.get_interval_estimates({"x": table}, nanmean, reps=reps,
                                                     confidence_interval_size=CONFIDENCE)
    low, high = interval["x"]
    return mean.tolist(), low.tolist(), high.tolist()


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The Wilson score interval of a success rate, `successes` of `n` independent episodes: unlike
    the normal approximation it stays inside [0, 1] and is not empty at 0 or n successes (0 of 50:
    [0, 0.071])."""
    from statistics import NormalDist

    if n <= 0:
        return float("nan"), float("nan")
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


SPLIT_LOW, SPLIT_HIGH = 0.1, 0.5
"""A configuration's seeds split when, on a success rate, some end at or below SPLIT_LOW (near 0) while
others end at or above SPLIT_HIGH (they solve the level): an IQM and its interval over the seeds then
describe no seed (finals 0.70, 0.73, 0.28, 0.02, 0.00: IQM 0.333 [0.007, 0.720], tests/test_report_seeds.py)."""


def seeds_split(scores, score_name: str) -> bool:
    """Whether one configuration's per-seed final scores split (`SPLIT_LOW`, `SPLIT_HIGH`); only a
    success rate has the fixed range the rule needs."""
    scores = np.asarray([s for s in scores if s is not None], dtype=float)
    scores = scores[~np.isnan(scores)]
    return bool(score_name == "success rate" and len(scores) >= 2 and
                scores.min() <= SPLIT_LOW and scores.max() >= SPLIT_HIGH)


def in_window(steps: np.ndarray, end: int, every: int) -> np.ndarray:
    """Which updates (by their global step) fall in the curve point ending at frame `end`: the window
    (F - every, end] with F the window's start on the `every` grid (a last, shorter window ends at the
    run's last step)."""
    return (steps > (end - 1) // every * every) & (steps <= end)
