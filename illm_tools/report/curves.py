"""Learning curves from run folders: the suite's score against frames, grouped by method over seeds.

Each run's `metrics.csv` gives, per update, the score of the episodes that finished in it (the
suite's: success rate for BabyAI and MiniHack, Crafter score, Atari's mean return; runs written
before the score column existed: their success rate) and how many there were; a curve point at
frame F is the episode-weighted mean over the window (F - every, F]. For Crafter it is the score of the
window's episodes taken together, from the achievements' rates pooled over them (`achievements.py`: a
geometric mean of success rates does not average).

Grouping. Runs are seeds of one configuration when their config.json agree on everything but the
settings that do not change what is learned (`NOT_LEARNED`: seed, folders, threads, resume). A
group is labelled by its env, its method, and the settings in which it differs from other runs of
the same env and method ("illm (ext_coef 2)"), so runs of different configurations are never
averaged as seeds; two runs of one configuration with the same seed are refused (a copied folder
would count twice).
"""

from __future__ import annotations

import csv
import json
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.report import stats


NOT_LEARNED = frozenset({"seed", "run_dir", "resume", "threads", "device", "llm_device", "llm_threads", "new_setup", "heads_bf16", "cache"})
"""config.json settings that may differ between seeds of one configuration (where a run is, how
it uses the CPU, numerics chosen by timing, and which cache folder holds its targets)."""


@dataclass
class Curve:
    run: str
    config: dict
    env_id: str
    seed: int
    frames: list[int]
    success: list[float]
    coverage: float
    """Mean share of rollout steps that had an LLM target."""
    hit_rate: float
    """Mean share of rollout steps found in the cache before the live fallback."""
    last_step: int
    """Frames the run was trained for (its last logged update)."""
    lengths: list[float]
    """Per curve point, the episode-weighted mean length (steps) of the episodes that ended in its window
    (NaN where none did, or the run logged no episodic_length)."""


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
                for name in ("target_coverage", "cache_hit_rate", "episodic_length"):
                    float(row.get(name) or 0)
            except (ValueError, KeyError) as e:
                raise DamagedFileError(f"{path} line {reader.line_num} is damaged ({e}): the run's metrics.jsonl "
                                       "holds the same rows; restore metrics.csv from a copy") from None
            rows.append(row)
    return rows


def _score(row: dict) -> float:
    """A row's score (its success rate in runs written before the score column existed)."""
    value = row.get("score") or row.get("success_rate")
    return float(value) if value else 0.0


def load_curve(run_dir: Path, every: int) -> Curve:
    from illm_tools.report.achievements import window_scores
    from illm_tools.rl.compare import comparable
    from illm_tools.rl.saved import read_run

    cfg, csv_path = comparable(read_run(run_dir).settings), run_dir / "metrics.csv"
    if not csv_path.is_file():
        raise UsageError(f"{run_dir} is not a training run (no metrics.csv): pass folders of `illm train`")
    rows = read_metrics_csv(csv_path)
    steps = np.array([int(r["global_step"]) for r in rows])
    eps = np.array([float(r["episodes"] or 0) for r in rows])
    succ = np.array([_score(r) for r in rows])
    length = np.array([float(r.get("episodic_length") or "nan") for r in rows])
    frames, points, lengths = [], [], []
    last_step = int(steps.max(initial=0))
    ends = list(range(every, last_step + 1, every))
    if last_step % every and last_step > every // 2:  # a last, shorter window up to the run's end
        ends.append(last_step)
    for end in ends:
        window = stats.in_window(steps, end, every)
        n = eps[window].sum()
        frames.append(end)
        points.append(float((succ[window] * eps[window]).sum() / n) if n else float("nan"))
        timed = window & (eps > 0) & ~np.isnan(length)
        m = eps[timed].sum()
        lengths.append(float((length[timed] * eps[timed]).sum() / m) if m else float("nan"))
    crafter = window_scores(run_dir, ends, every)  # a window's episodes pooled, where the run logs achievements
    if crafter is not None:
        points = crafter

    def mean_of(column: str) -> float:
        values = [float(r[column]) for r in rows if r.get(column)]
        return float(np.mean(values)) if values else 0.0

    return Curve(str(run_dir), cfg, cfg["env_id"], int(cfg["seed"]), frames, points,
                 mean_of("target_coverage"), mean_of("cache_hit_rate"), last_step, lengths)


def _setting(value) -> str:
    """A setting's value as a label shows it: numbers plainly, lists joined with "+" (language tasks
    as the paper's Table 2 writes them), dicts as key=value, nothing as "-"."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return "+".join(map(_setting, value)) or "-"
    if isinstance(value, dict):
        return ",".join(f"{k}={_setting(v)}" for k, v in sorted(value.items())) or "-"
    return str(value)


def _learned(cfg: dict) -> str:
    """The canonical form of what a run learns with (its config.json minus NOT_LEARNED)."""
    return json.dumps({k: v for k, v in cfg.items() if k not in NOT_LEARNED}, sort_keys=True, default=str)


def group_settings(configs: list[dict]) -> list[dict[str, str]]:
    """Per run, the settings in which its configuration differs from other configurations of the
    same env and method, as labels show them ({"ext_coef": "2", "lambda_a": "0.1"})."""
    method = [c.get("method", c.get("mode", "?")) for c in configs]
    out = []
    for i, cfg in enumerate(configs):
        peers = [c for j, c in enumerate(configs) if c["env_id"] == cfg["env_id"] and method[j] == method[i]]
        varying = sorted({k for c in peers for k in set(c) | set(cfg)
                          if k not in NOT_LEARNED and c.get(k) != cfg.get(k)})
        out.append({k: _setting(cfg.get(k)) for k in varying})
    return out


def group_labels(configs: list[dict], runs: list[str] | None = None) -> list[str]:
    """Each run's group label: its method, plus the settings in which its configuration differs
    from other configurations of the same env and method ("illm (ext_coef 2, lambda_a 0.1)").
    Where that needs settings and the runs are an `illm experiment`'s (`runs`: their folders,
    RESULTS/ENV/LABEL/seedN beside RESULTS/spec.yaml), the grid's own label names the group
    ("illm-annotator=student"), as long as it names that one configuration alone."""
    settings = group_settings(configs)
    labels = [c.get("method", c.get("mode", "?")) + (f" ({', '.join(f'{k} {v}' for k, v in s.items())})" if s else "")
              for c, s in zip(configs, settings)]
    if runs is None:
        return labels
    keys = [(c["env_id"], label) for c, label in zip(configs, labels)]
    grid: dict[tuple, set] = {}  # (env, a label with settings) -> the grid labels of its runs
    for key, s, run in zip(keys, settings, runs):
        if s:
            grid.setdefault(key, set()).add(_grid_label(Path(run)))
    named = {key: next(iter(gs)) for key, gs in grid.items() if len(gs) == 1 and None not in gs}
    plain = {key for key, s in zip(keys, settings) if not s}
    uses = Counter((env, g) for (env, _), g in named.items())
    return [named[key] if key in named and uses[(key[0], named[key])] == 1 and (key[0], named[key]) not in plain
            else key[1] for key in keys]


def _grid_label(run: Path) -> str | None:
    """The label of an `illm experiment` run (RESULTS/ENV/LABEL/seedN, RESULTS/spec.yaml), else None."""
    from illm_tools.experiment import SPEC_COPY

    if run.name.startswith("seed") and (run.parent.parent.parent / SPEC_COPY).is_file():
        return run.parent.name
    return None


def _reads_targets(cfg: dict) -> bool:
    """Whether the run's method reads LLM targets (so its target coverage means something)."""
    from illm_tools.intrinsic.registry import METHODS

    method = METHODS.get(cfg.get("method", cfg.get("mode", "")))
    return method.needs_targets if method is not None else True


def summarise(run_dirs: list[Path], every: int) -> dict:
    """{(env, label): {"frames", "mean", "std", "seeds", "runs", "coverage", "hit_rate"}}, one
    entry per configuration (see the module docstring), plus the runs shorter than `every` under
    each group's "short_runs" (they give no curve point), and its runs' `Curve`s as read (under
    "curves"; not JSON): each run is read once, so a run still training when a report reads the
    grid gives every table the same points."""
    if every <= 0:
        raise UsageError(f"--every must be positive, got {every}")
    curves = [load_curve(Path(run), every) for run in run_dirs]
    if not curves:
        raise UsageError("no run folders given: pass folders written by `illm train`")
    labels = group_labels([c.config for c in curves], [c.run for c in curves])
    settings = dict(zip(labels, group_settings([c.config for c in curves])))
    groups: dict[tuple[str, str], list[Curve]] = {}
    for curve, label in zip(curves, labels):
        groups.setdefault((curve.env_id, label), []).append(curve)
    out = {}
    for key, members in sorted(groups.items()):
        by_config: dict[tuple[str, int], str] = {}
        for c in members:
            other = by_config.setdefault((_learned(c.config), c.seed), c.run)
            if other != c.run:
                raise UsageError(f"{other} and {c.run} are the same configuration with the same seed {c.seed} (a "
                                 "copy?): pass one of them")
        long = [c for c in members if c.frames]
        frames = sorted(set.intersection(*(set(c.frames) for c in long))) if long else []  # points every seed has
        table = np.array([[dict(zip(c.frames, c.success))[f] for f in frames] for c in long],
                         dtype=float).reshape(len(long), len(frames))
        with np.errstate(all="ignore"), warnings.catch_warnings():  # windows with no finished episode stay NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            mean, std = (np.nanmean(table, 0), np.nanstd(table, 0)) if long else (np.zeros(0), np.zeros(0))
        out[key] = {"method": members[0].config.get("method", members[0].config.get("mode", "?")), "settings": settings[key[1]],
                    "reads_targets": _reads_targets(members[0].config),
                    "frames": frames, "mean": mean.tolist(), "std": std.tolist(), "seeds": sorted(c.seed for c in long),
                    "runs": [c.run for c in long], "short_runs": {c.run: c.last_step for c in members if not c.frames},
                    "curves": long,
                    "coverage": float(np.mean([c.coverage for c in members])),
                    "hit_rate": float(np.mean([c.hit_rate for c in members]))}
    return out
