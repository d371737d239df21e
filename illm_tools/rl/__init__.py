"""PPO for iLLM: configuration, networks, rollout storage, the trainer and run-dir checkpoints.

Names are imported on first use (PEP 562), so that `illm_tools.rl.config` (read by the command
line to build `illm train`'s options) does not import torch.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "load_checkpoint": "checkpoint", "load_policy": "checkpoint", "TrainConfig": "config",
    "GridMissionNet": "networks", "MissionVocab": "networks", "Trainer": "ppo", "make_pool": "run",
    "Rollout": "storage", "gae": "storage", "two_stream_advantages": "storage", "run_config": "build",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
