"""Learning curves from run folders: success rate against frames, grouped by method over seeds.

Each run's `metrics.csv` gives, per update, the success rate of the episodes that finished in it
and how many there were; a curve point at frame F is the episode-weighted success rate over the
window (F - every, F]. Runs are grouped by the method (and env) in their config.json.
"""

from __future__ import annotations

import csv
import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from illm_tools.errors import UsageError


@dataclass
class Curve:
    run: str
    method: str
    env_id: str
    seed: int
    frames: list[int]
    success: list[float]
    coverage: float
    """Mean share of rollout steps that had an LLM target."""
    hit_rate: float
    """Mean share of rollout steps found in the cache before the live fallback."""


def read_metrics_csv(path: Path) -> list[dict]:
    """metrics.csv's rows, refusing (one line naming the line) a file cut short, a row with missing
    or extra fields, or numbers that do not parse: what a damaged or hand-edited file shows."""
    from illm_tools.errors import DamagedFileError

    with open(path, "rb") as fh:
        size = fh.seek(0, 2)
        fh.seek(max(size - 1, 0))
        if size and fh.read(1) != b"\n":  # the trainer ends every row with one
            raise DamagedFileError(f"{path} is cut short (its last row has no line end): the run's metrics.jsonl "
                                   "holds the same rows; restore metrics.csv from a copy")
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        rows = []
        for row in reader:
            try:
                if None in row or any(v is None for v in row.values()):
                    raise ValueError("wrong number of fields")
                int(row["global_step"]), float(row["episodes"] or 0), float(row["success_rate"] or 0)
                for name in ("target_coverage", "cache_hit_rate"):
                    float(row.get(name) or 0)
            except (ValueError, KeyError) as e:
                raise DamagedFileError(f"{path} line {reader.line_num} is damaged ({e}): the run's metrics.jsonl "
                                       "holds the same rows; restore metrics.csv from a copy") from None
            rows.append(row)
    return rows


def load_curve(run_dir: Path, every: int) -> Curve:
    cfg_path, csv_path = run_dir / "config.json", run_dir / "metrics.csv"
    if not cfg_path.is_file() or not csv_path.is_file():
        raise UsageError(f"{run_dir} is not a training run (no config.json / metrics.csv): pass folders of `illm train`")
    cfg = json.loads(cfg_path.read_text())
    rows = read_metrics_csv(csv_path)
    steps = np.array([int(r["global_step"]) for r in rows])
    eps = np.array([float(r["episodes"] or 0) for r in rows])
    succ = np.array([float(r["success_rate"]) if r["success_rate"] else 0.0 for r in rows])
    frames, points = [], []
    last_step = int(steps.max(initial=0))
    ends = list(range(every, last_step + 1, every))
    if last_step % every and last_step > every // 2:  # a last, shorter window up to the run's end
        ends.append(last_step)
    for end in ends:
        window = (steps > (end - 1) // every * every) & (steps <= end)
        n = eps[window].sum()
        frames.append(end)
        points.append(float((succ[window] * eps[window]).sum() / n) if n else float("nan"))
    def mean_of(column: str) -> float:
        values = [float(r[column]) for r in rows if r.get(column)]
        return float(np.mean(values)) if values else 0.0

    return Curve(str(run_dir), method_label(cfg), cfg["env_id"], int(cfg["seed"]), frames, points,
                 mean_of("target_coverage"), mean_of("cache_hit_rate"))


def method_label(cfg: dict) -> str:
    """The method a run is grouped under: its mode, plus the bonus weights where they differ from
    the paper's (so runs of one mode with other weights are not averaged together)."""
    from illm_tools.rl.config import BONUS_PRESETS  # the schema of the config.json it reads

    if cfg["mode"] != "illm":
        return cfg["mode"]
    changed = [f"{k} {cfg[k]:g}" for k, v in BONUS_PRESETS["paper"].items() if cfg.get(k, v) != v]
    return cfg["mode"] + (f" ({', '.join(changed)})" if changed else "")


def summarise(run_dirs: list[Path], every: int) -> dict:
    """{(env, method): {"frames": [...], "mean": [...], "std": [...], "seeds": n, ...}}."""
    if every <= 0:
        raise UsageError(f"--every must be positive, got {every}")
    groups: dict[tuple[str, str], list[Curve]] = {}
    for run in run_dirs:
        curve = load_curve(Path(run), every)
        groups.setdefault((curve.env_id, curve.method), []).append(curve)
    out = {}
    for key, curves in sorted(groups.items()):
        frames = sorted(set.intersection(*(set(c.frames) for c in curves)))  # points every seed has
        table = np.array([[dict(zip(c.frames, c.success))[f] for f in frames] for c in curves])
        with np.errstate(all="ignore"), warnings.catch_warnings():  # windows with no finished episode stay NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            mean, std = np.nanmean(table, 0), np.nanstd(table, 0)
        out[key] = {"frames": frames, "mean": mean.tolist(), "std": std.tolist(), "seeds": sorted(c.seed for c in curves),
                    "coverage": float(np.mean([c.coverage for c in curves])),
                    "hit_rate": float(np.mean([c.hit_rate for c in curves]))}
    return out
