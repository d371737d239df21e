"""The files of a training run directory, and loading a trained run's policy for other stages.

Owns `run_dir/checkpoint.pt` and `checkpoint.prev.pt`, `run_dir/config.json` (`write_config`,
`read_config`: `illm_tools.rl.names`, re-exported), `run_dir/metrics.jsonl` (one JSON object per update, every metric),
`run_dir/metrics.csv` (the same rows, a fixed set of columns, for spreadsheets and `illm report`),
TensorBoard events when asked and `load_policy`, which rebuilds the network from config.json + the
checkpoint for `collect` / `eval`.

Checkpoints (format 2) hold the torch-saved state as bytes beside their sha256, so a damaged file
is detected, never loaded as other weights. A new checkpoint is written to a temporary file,
fsynced, and renamed over checkpoint.pt after the previous one was renamed to checkpoint.prev.pt
(the directory fsynced after each): at every moment one of the two is whole. `load_checkpoint`
falls back to the previous checkpoint, saying so, when the latest is missing or damaged. Format-1
checkpoints (no digest) still load.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
from pathlib import Path

import numpy as np
import torch

from illm_tools import durable
from illm_tools.errors import DamagedFileError, UsageError
from illm_tools.rl.names import CONFIG_NAME, flat_settings, read_config, write_config  # noqa: F401  (re-exported)

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"
PREVIOUS_NAME = "checkpoint.prev.pt"
CHECKPOINT_VERSION = 2
READABLE_VERSIONS = (1, 2)
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


def save_checkpoint(run_dir: Path, state: dict) -> Path:
    """Write `state` to run_dir/checkpoint.pt with its digest, keeping the one it replaces as
    checkpoint.prev.pt (see the module docstring for the order of the renames)."""
    run_dir = Path(run_dir)
    path, previous, tmp = run_dir / CHECKPOINT_NAME, run_dir / PREVIOUS_NAME, run_dir / f".{CHECKPOINT_NAME}.tmp"
    buffer = io.BytesIO()
    torch.save(state, buffer)
    payload = buffer.getvalue()
    with durable.staged(path, tmp=tmp) as fh:  # e.g. a full disk: the checkpoints in place stay as they were
        torch.save({"format_version": CHECKPOINT_VERSION, "sha256": hashlib.sha256(payload).hexdigest(),
                    "state": payload}, fh)
    if path.exists():
        durable.commit(path, previous)
    return durable.commit(tmp, path)


def _read_checkpoint(path: Path) -> dict:
    """One checkpoint file's state; DamagedFileError (or UsageError for another format) if not whole."""
    try:
        outer = torch.load(path, map_location="cpu", weights_only=True)
        version = outer.get("format_version") if isinstance(outer, dict) else None
    except Exception as e:  # noqa: BLE001 - torch.load raises many kinds on a damaged file
        raise DamagedFileError(f"{path} is damaged ({type(e).__name__})") from None
    if version not in READABLE_VERSIONS:
        raise UsageError(f"{path} has checkpoint format {version!r}; this illm reads formats "
                         f"{', '.join(map(str, READABLE_VERSIONS))}")
    if version == 1:
        return outer
    payload = outer.get("state")
    if not isinstance(payload, bytes) or hashlib.sha256(payload).hexdigest() != outer.get("sha256"):
        raise DamagedFileError(f"{path} is damaged (its contents differ from their recorded sha256)")
    try:
        return torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001
        raise DamagedFileError(f"{path} is damaged ({type(e).__name__})") from None


_FALLBACKS_SAID: set[tuple] = set()


def load_checkpoint(run_dir: Path) -> dict:
    """The last whole checkpoint of a run: checkpoint.pt, or checkpoint.prev.pt (saying so) when
    the latest is missing or damaged. One line (UsageError / DamagedFileError) when neither is."""
    run_dir = Path(run_dir)
    path, previous = run_dir / CHECKPOINT_NAME, run_dir / PREVIOUS_NAME
    if not path.exists() and not previous.exists():
        raise UsageError(f"no checkpoint at {path}; train first or drop --resume")
    try:
        if not path.exists():
            raise DamagedFileError(f"{path} is missing")
        return _read_checkpoint(path)
    except DamagedFileError as latest:
        if not previous.exists():
            raise DamagedFileError(f"{latest}, and there is no previous checkpoint: train into a new --out") from None
        try:
            state = _read_checkpoint(previous)
        except DamagedFileError as prev:
            raise DamagedFileError(f"{latest}, and so is the previous one ({prev}): train into a new --out") from None
        said = (str(path), path.stat().st_mtime_ns if path.exists() else None)
        if said not in _FALLBACKS_SAID:  # a run reads its checkpoint more than once: say it once
            _FALLBACKS_SAID.add(said)
            log.warning("%s; using the previous checkpoint %s (update %s, %s frames)", latest, previous,
                        state.get("update"), f"{int(state.get('global_step', 0)):,}")
        return state


# settings a resumed run may change; any other difference is refused
RESUMABLE_CHANGES = frozenset({"total_steps", "resume", "device", "llm_device", "checkpoint_every", "checkpoint_minutes", "tensorboard", "live_budget", "threads",
                               "llm_threads", "live_mode", "new_setup", "heads_bf16", "run_dir", "cache", "vector",
                               "annotator"})


def check_resumable(state: dict, cfg, action_names: list[str]) -> None:
    """Refuse to resume a checkpoint under other settings or another action list."""
    # compared under the flat names (`illm_tools.rl.names`): a checkpoint of any version, the LLM's device left to llm_device
    saved, now = flat_settings(state["config"]), flat_settings(cfg.to_dict())
    # a setting added after the checkpoint was written counts at its default value
    defaults = flat_settings(type(cfg)().to_dict()) if any(k not in saved for k in now) else {}
    changed = sorted(k for k in now if saved.get(k, defaults.get(k)) != now[k] and k not in RESUMABLE_CHANGES)
    if changed:
        raise UsageError(f"cannot resume with changed settings {changed}; "
                         "only total_steps and checkpointing may change")
    if state["action_names"] != list(action_names):
        raise UsageError(f"the checkpoint was trained with actions {state['action_names']}, "
                         f"the environment offers {list(action_names)}; use the same action space")


class TrainedPolicy:
    """A trained run's actor, acting on the pool's `PoolObs` (sampled, or greedy)."""

    def __init__(self, net, vocab, *, name: str, greedy: bool = False, seed: int = 0, frames: int = 0,
                 states=None):
        self.net, self.vocab, self.name, self.greedy = net.eval(), vocab, name, greedy
        self.frames = frames
        """Frames the policy was trained for."""
        self.generator = torch.Generator().manual_seed(seed)
        self.states = states
        """The run's state source (`illm_tools.rl.states`) where its network reads a context (hop's Z_h)."""
        self._last: tuple | None = None  # (observations, actions) of the last call

    @torch.no_grad()
    def act(self, obs) -> np.ndarray:
        images = torch.as_tensor(obs.images)
        missions = torch.as_tensor(self.vocab.encode(obs.missions))
        context = None
        if self.states is not None:  # the windows follow the episodes: a state with step 0 began a new one
            if self._last is not None:
                self.states.advance(self._last[0], self._last[1].tolist(), (np.asarray(obs.steps) == 0).tolist(), obs)
            context = self.states.current(obs)[1]
        logits = self.net(images, missions, context).logits
        if self.greedy:
            actions = logits.argmax(-1).numpy()
        else:
            actions = torch.multinomial(logits.softmax(-1), 1, generator=self.generator).squeeze(-1).numpy()
        self._last = obs, actions
        return actions


def load_policy(run_dir: str | Path, pool, *, greedy: bool = False, seed: int = 0) -> TrainedPolicy:
    """Rebuild a run's network for `pool` (whose action list must match) and load its weights."""
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.rl.config import TrainConfig
    from illm_tools.rl.networks import make_network
    from illm_tools.rl.states import make_states
    from illm_tools.tasks.registry import get_task

    run_dir = Path(run_dir)
    cfg = TrainConfig.from_dict(read_config(run_dir))
    state = load_checkpoint(run_dir)
    names = list(pool.action_names)
    if state["action_names"] != names:
        raise UsageError(f"the run was trained with actions {state['action_names']}, "
                         f"the environment offers {names}; use the same --action-space")
    vocab = pool.suite.mission_vocab(cfg.mission_max_len)
    method = get_method(cfg.method)
    text_heads = [get_task(t).head for t in cfg.text_tasks]  # the iLLM heads the method's bonus put on the network
    dim = state["model"][f"{text_heads[0]}.2.weight"].shape[0] if text_heads else cfg.embedding_dim
    states = make_states(cfg, pool.suite, tuple(state["image_shape"]), names, needs_records=False,
                         num_envs=pool.num_envs)
    net = make_network(method, cfg.env_id, len(names), image_shape=tuple(state["image_shape"]),
                       vocab_size=len(vocab), network_options=cfg.network_options,
                       embedding_dim=dim if method.policy_heads else None, tasks=cfg.tasks,
                       head_hidden=cfg.head_hidden, heads_bf16=cfg.heads_bf16,  # as trained: no probe
                       context_dim=states.context_dim)
    net.load_state_dict(state["model"])
    return TrainedPolicy(net, vocab, name=f"run:{run_dir.name}@{state['global_step']}",
                         greedy=greedy, seed=seed, frames=int(state["global_step"]),
                         states=states if states.context_dim else None)
