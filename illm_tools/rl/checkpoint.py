"""The files of a training run directory, and loading a trained run's policy for other stages.

Owns `run_dir/checkpoint.pt` (written atomically: temporary file, fsync, rename, so a crash
leaves the previous checkpoint intact), `run_dir/metrics.jsonl` (one JSON object per update, every
metric), `run_dir/metrics.csv` (the same rows, a fixed set of columns, for spreadsheets and
`illm report`), TensorBoard events when asked and `load_policy`, which rebuilds the network from
`run_dir/config.json` + the checkpoint for `collect` / `eval`.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
import torch

from illm_tools.errors import UsageError

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_VERSION = 1
METRICS_NAME = "metrics.jsonl"
CSV_NAME = "metrics.csv"
# metrics.csv columns: metric keys without their charts/ or losses/ group; empty when not logged
CSV_COLUMNS = ("global_step", "update", "episodic_return", "episodic_length", "success_rate", "sps",
               "intrinsic_reward_a", "intrinsic_reward_hc", "cache_hit_rate", "target_coverage",
               "live_annotations", "no_target_steps", "episodes", "learning_rate", "policy_loss",
               "value_loss", "value_loss_int", "entropy", "approx_kl", "clipfrac", "explained_variance",
               "distill_action", "distill_summary", "live_queue", "adv_ext_abs", "adv_int_abs",
               "adv_int_ext_ratio", "return_ext", "return_int")


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
            rows = [r for r in self.path.read_text().splitlines()
                    if r.strip() and json.loads(r).get("update", 0) <= keep_until_update]
        self._rewrite(rows)
        self._fh = open(self.path, "a")
        self._csv_fh = open(self.csv_path, "a", newline="")
        self._csv = csv.writer(self._csv_fh)
        self._tb = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter  # heavy import, only when asked

            self._tb = SummaryWriter(str(run_dir))

    def _rewrite(self, rows: list[str]) -> None:
        """Start both files afresh with the given JSON rows (atomically each)."""
        for path, lines in ((self.path, [r + "\n" for r in rows]),
                            (self.csv_path, [",".join(CSV_COLUMNS) + "\n"]
                             + [",".join(map(str, csv_row(json.loads(r)))) + "\n" for r in rows])):
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text("".join(lines))
            os.replace(tmp, path)

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


def save_checkpoint(run_dir: Path, state: dict) -> Path:
    """Write `state` (plus a format version) to run_dir/checkpoint.pt atomically."""
    path = Path(run_dir) / CHECKPOINT_NAME
    tmp = path.with_suffix(".pt.tmp")
    with open(tmp, "wb") as fh:
        torch.save({"format_version": CHECKPOINT_VERSION, **state}, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def load_checkpoint(run_dir: Path) -> dict:
    """The last checkpoint of a run; raises UsageError when there is none or it is foreign."""
    path = Path(run_dir) / CHECKPOINT_NAME
    if not path.exists():
        raise UsageError(f"no checkpoint at {path}; train first or drop --resume")
    state = torch.load(path, map_location="cpu", weights_only=True)
    if state.get("format_version") != CHECKPOINT_VERSION:
        raise UsageError(f"{path} has checkpoint format {state.get('format_version')!r}; "
                         f"this illm reads format {CHECKPOINT_VERSION}")
    return state


# settings a resumed run may change; any other difference is refused
RESUMABLE_CHANGES = frozenset({"total_steps", "resume", "checkpoint_every", "tensorboard", "live_budget", "threads",
                               "llm_threads", "live_mode", "new_setup", "heads_bf16"})


def check_resumable(state: dict, cfg, action_names: list[str]) -> None:
    """Refuse to resume a checkpoint under other settings or another action list."""
    saved, now = state["config"], cfg.to_dict()
    # a setting added after the checkpoint was written counts at its default value
    defaults = type(cfg)().to_dict() if any(k not in saved for k in now) else {}
    changed = sorted(k for k in now if saved.get(k, defaults.get(k)) != now[k] and k not in RESUMABLE_CHANGES)
    if changed:
        raise UsageError(f"cannot resume with changed settings {changed}; "
                         "only total_steps and checkpointing may change")
    if state["action_names"] != list(action_names):
        raise UsageError(f"the checkpoint was trained with actions {state['action_names']}, "
                         f"the environment offers {list(action_names)}; use the same action space")


class TrainedPolicy:
    """A trained run's actor, acting on the pool's `PoolObs` (sampled, or greedy)."""

    def __init__(self, net, vocab, *, name: str, greedy: bool = False, seed: int = 0):
        self.net, self.vocab, self.name, self.greedy = net.eval(), vocab, name, greedy
        self.generator = torch.Generator().manual_seed(seed)

    @torch.no_grad()
    def act(self, obs) -> np.ndarray:
        images = torch.as_tensor(obs.images)
        missions = torch.as_tensor(self.vocab.encode(obs.missions))
        logits = self.net(images, missions).logits
        if self.greedy:
            return logits.argmax(-1).numpy()
        return torch.multinomial(logits.softmax(-1), 1, generator=self.generator).squeeze(-1).numpy()


def load_policy(run_dir: str | Path, pool, *, greedy: bool = False, seed: int = 0) -> TrainedPolicy:
    """Rebuild a run's network for `pool` (whose action list must match) and load its weights."""
    from illm_tools.rl.config import TrainConfig
    from illm_tools.rl.networks import GridMissionNet, MissionVocab

    run_dir = Path(run_dir)
    config_path = run_dir / "config.json"
    if not config_path.exists():
        raise UsageError(f"{run_dir} is not a training run (no config.json)")
    cfg = TrainConfig.from_dict(json.loads(config_path.read_text()))
    state = load_checkpoint(run_dir)
    names = list(pool.action_names)
    if state["action_names"] != names:
        raise UsageError(f"the run was trained with actions {state['action_names']}, "
                         f"the environment offers {names}; use the same --action-space")
    vocab = MissionVocab(cfg.mission_max_len)
    heads = "f_hc.2.weight" in state["model"]  # the method's bonus put the iLLM heads on the network
    net = GridMissionNet(len(names), vocab_size=len(vocab),
                         embedding_dim=state["model"]["f_hc.2.weight"].shape[0] if heads else None,
                         head_hidden=cfg.head_hidden, image_shape=tuple(state["image_shape"][:2]))
    net.load_state_dict(state["model"])
    return TrainedPolicy(net, vocab, name=f"run:{run_dir.name}@{state['global_step']}",
                         greedy=greedy, seed=seed)
