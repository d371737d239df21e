"""PPO for iLLM: configuration, networks, rollout storage, the trainer and run-dir checkpoints.

Names are imported on first use (PEP 562), so that `illm_tools.rl.config` (read by the command
line to build `illm train`'s options) does not import torch. The methods this layer brings (chibit)
are registered on import (`methods.py`, light).
"""

from __future__ import annotations

import importlib

from illm_tools.rl import methods as _methods  # noqa: F401  (registers this layer's methods: chibit)

_EXPORTS = {
    "load_checkpoint": "checkpoint", "load_policy": "policy", "read_run": "saved", "TrainConfig": "config",
    "GridMissionNet": "networks", "MissionVocab": "networks", "Trainer": "ppo", "make_pool": "run",
    "Rollout": "storage", "gae": "storage", "two_stream_advantages": "storage", "run_config": "build",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
