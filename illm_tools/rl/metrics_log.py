"""A training run's metrics: `run_dir/metrics.jsonl` (one JSON object per update, every metric),
`run_dir/metrics.csv` (the same rows, a fixed set of columns, for spreadsheets and `illm report`)
and TensorBoard events when asked, written by `MetricsLog`.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from illm_tools import durable
from illm_tools.errors import DamagedFileError

METRICS_NAME = "metrics.jsonl"
CSV_NAME = "metrics.csv"
# metrics.csv columns: metric keys without their charts/ or losses/ group; empty when not logged
CSV_COLUMNS = ("global_step", "update", "episodic_return", "episodic_length", "success_rate", "sps",
               "intrinsic_reward_a", "intrinsic_reward_hc", "cache_hit_rate", "target_coverage",
               "live_annotations", "no_target_steps", "episodes", "learning_rate", "policy_loss",
               "value_loss", "value_loss_int", "entropy", "approx_kl", "clipfrac", "explained_variance",
               "distill_action", "distill_summary", "live_queue", "adv_ext_abs", "adv_int_abs",
               "adv_int_ext_ratio", "return_ext", "return_int", "intrinsic_reward", "score")
# (a bonus's own scalars, e.g. rnd_error, ngu_lifelong, ellm_paid_steps, are in metrics.jsonl under charts/)


def csv_row(metrics: dict) -> list:
    flat = {key.split("/", 1)[-1]: value for key, value in metrics.items()}
    return ["" if flat.get(c) is None else flat[c] for c in CSV_COLUMNS]


class MetricsLog:
    """Appends one JSON line per update to metrics.jsonl and mirrors scalars to TensorBoard."""

    def __init__(self, run_dir: Path, *, tensorboard: bool, keep_until_update: int | None = None):
        self.path = Path(run_dir) / METRICS_NAME
        self.csv_path = Path(run_dir) / CSV_NAME
        rows: list[str] = []
        if keep_until_update is not None and self.path.exists():
            # on resume, drop rows logged after the checkpoint: they are about to be redone
            rows = [r for r in self._rows() if r["update"] <= keep_until_update]
            rows = [json.dumps(r) for r in rows]
        self._rewrite(rows)
        self._fh = open(self.path, "a")
        self._csv_fh = open(self.csv_path, "a", newline="")
        self._csv = csv.writer(self._csv_fh)
        self._tb = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter  # heavy import, only when asked

            self._tb = SummaryWriter(str(run_dir))

    def _rows(self) -> list[dict]:
        """metrics.jsonl's rows. A last line cut short (a process killed while writing it, after its
        checkpoint) is dropped; a damaged line before it is refused in one line."""
        lines = self.path.read_text(errors="replace").splitlines()
        rows = []
        for n, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
                row["update"] = int(row.get("update", 0))
            except (ValueError, TypeError, AttributeError):
                if n == len(lines):
                    break
                raise DamagedFileError(f"{self.path} line {n} is damaged: restore the file from a copy, or train "
                                       "into a new --out") from None
            rows.append(row)
        return rows

    def _rewrite(self, rows: list[str]) -> None:
        """Start both files afresh with the given JSON rows (atomically each)."""
        for path, lines in ((self.path, [r + "\n" for r in rows]),
                            (self.csv_path, [",".join(CSV_COLUMNS) + "\n"]
                             + [",".join(map(str, csv_row(json.loads(r)))) + "\n" for r in rows])):
            durable.write_text(path, "".join(lines))

    def write(self, metrics: dict) -> None:
        self._fh.write(json.dumps(metrics) + "\n")
        self._fh.flush()
        self._csv.writerow(csv_row(metrics))
        self._csv_fh.flush()
        if self._tb is not None:
            step = int(metrics["global_step"])
            for key, value in metrics.items():
                if "/" in key:
                    self._tb.add_scalar(key, value, step)

    def close(self) -> None:
        self._fh.close()
        self._csv_fh.close()
        if self._tb is not None:
            self._tb.close()


class Means:
    """Running sums of logged values (tensors stay tensors: on a GPU, one wait for the device when the
    means are read), averaged over what was added: a PPO update's minibatches."""

    def __init__(self):
        self.sums: dict = {}  # name -> a sum: a tensor (or float) as logged
        self.counts: dict[str, int] = {}

    def add(self, logs: dict) -> None:
        for k, v in logs.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
            self.counts[k] = self.counts.get(k, 0) + 1

    def means(self) -> dict[str, float]:
        return {k: float(v) / self.counts[k] for k, v in self.sums.items()}
