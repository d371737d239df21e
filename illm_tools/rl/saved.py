"""A saved run, read one way: its folder's config.json (`read_config`, `write_config`) and
checkpoint (`illm_tools.rl.checkpoint`), read together by `read_run` for every reader (a resumed
run, `illm eval`, `illm report`, `illm collect --policy`, the experiment planner).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

from illm_tools import durable
from illm_tools.errors import DamagedFileError, UsageError

CONFIG_NAME = "config.json"
"""A run folder's settings file (`write_config`, `read_config`)."""


def write_config(run_dir: Path, config: dict) -> None:
    """Write run_dir/config.json atomically (temporary file, fsync, rename)."""
    durable.write_text(Path(run_dir) / CONFIG_NAME, json.dumps(config, indent=2))


def read_config(run_dir: Path) -> dict:
    """run_dir/config.json as written by `illm train` (any version's, in this version's shape:
    `illm_tools.rl.config.upgrade_config`); one line when it is absent or damaged."""
    from illm_tools.rl.config import upgrade_config

    path = Path(run_dir) / CONFIG_NAME
    if not path.is_file():
        raise UsageError(f"{run_dir} is not a training run (no {CONFIG_NAME}): pass a folder written by `illm train`")
    try:
        config = json.loads(path.read_text())
        if not isinstance(config, dict) or "env_id" not in config or not ({"method", "mode"} & set(config)):
            raise ValueError("not a run's settings")
        config = upgrade_config(config)
    except (ValueError, UnicodeDecodeError) as e:
        raise DamagedFileError(f"{path} is damaged ({type(e).__name__}): the checkpoint holds the same settings; "
                               "restore the file from a copy") from None
    return config


class SavedRun:
    """A run folder as written by `illm train`: its settings (`settings`: config.json in this
    version's shape; `config`: as a `TrainConfig`) and its checkpoint (`checkpoint`, read once, when
    first asked: the last whole one, `illm_tools.rl.checkpoint.load_checkpoint`)."""

    def __init__(self, run_dir: Path, settings: dict):
        self.run_dir, self.settings = Path(run_dir), settings

    @functools.cached_property
    def config(self):
        """The run's `TrainConfig` (in its folder as it is now: the folder may have moved)."""
        from illm_tools.rl.config import TrainConfig

        return TrainConfig.from_dict({**self.settings, "run_dir": str(self.run_dir)})

    @functools.cached_property
    def checkpoint(self) -> dict:
        """The run's last whole checkpoint (one line when it has none, or none is whole)."""
        from illm_tools.rl.checkpoint import load_checkpoint

        return load_checkpoint(self.run_dir)

    @property
    def frames(self) -> int:
        """Frames the checkpoint was trained for."""
        return int(self.checkpoint["global_step"])


def read_run(run_dir: Path) -> SavedRun:
    """The saved run in `run_dir` (its config.json read now, one line when absent or damaged; its
    checkpoint when first asked)."""
    return SavedRun(run_dir, read_config(run_dir))


def with_recorded_choices(cfg, saved: SavedRun | None):
    """`cfg` of a resumed run with the choice its `saved` run recorded where `cfg` leaves it to
    auto: the action space the run resolved when it started (`TrainConfig.resolved`), so that a run
    resumed from the Python API trains on the actions it began with. Without a saved run: `cfg`."""
    import dataclasses

    if saved is None or cfg.action_space != "auto":
        return cfg
    return dataclasses.replace(cfg, action_space=saved.settings.get("action_space", "auto"))
