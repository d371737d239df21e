"""A run's settings by name: the composed `TrainConfig` (its `llm: LLMSpec` and `illm: ILLMConfig`)
seen under the flat names its options, experiment specs and older runs' config.json use.

`TrainConfig` holds the LLM as one `LLMSpec` and iLLM's settings as one `ILLMConfig`; every setting
still has one flat name, the name of its option (`--model` -> model, `--dtype` -> model_dtype,
`--lambda-a` -> lambda_a) and of its key in config.json files written before the config was
composed. `NESTED` maps each such name to where it lives now; `upgrade_config` reads a config of any
version (flat, composed or a mix: flat names win) into this version's shape, and `flat_settings`
gives a config's settings under the flat names, values as the config holds them (the LLM's model
named as `LLMSpec` names it), which is how runs are compared (resume, `illm report`). A run folder's
config.json is written and read here (`write_config`, `read_config`: any version's, in this shape).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path

from illm_tools import durable
from illm_tools.errors import DamagedFileError, UsageError

CONFIG_NAME = "config.json"
"""A run folder's settings file (`write_config`, `read_config`)."""
RENAMED = {"mode": "method"}
"""Settings renamed since runs were first written (old name -> new): config.json files and
checkpoints of older runs are read under the new names."""

GROUPS = {
    "llm": {"backend": "backend", "model": "model", "model_dtype": "dtype", "quant": "quant",
            "oracle_noise": "oracle_noise", "endpoint": "endpoint", "api_key_env": "api_key_env",
            "embed_endpoint": "embed_endpoint"},
    "illm": {name: name for name in ("lambda_a", "beta_hc", "tasks", "task_weights", "summary_loss",
                                     "action_similarity")},
}
"""Each composed field of TrainConfig: flat name -> the field of its config (`LLMSpec`, `ILLMConfig`)."""
NESTED = {flat: (group, name) for group, names in GROUPS.items() for flat, name in names.items()}
"""Flat name -> (TrainConfig field, field of that config)."""
DERIVED = ("embedding_dim",)
"""Settings older versions wrote that are now derived from others (`TrainConfig.embedding_dim`:
the LLM's hidden size): dropped on reading."""
LLM_NOT_SETTINGS = ("device", "offline", "batch_tokens")
"""`LLMSpec` fields that are no run setting: its device is `TrainConfig.llm_device` (default: the
run's `device`), a run never downloads what it lacks, and its live annotator's batches take the
default budget."""


def group_dict(group: str, value) -> dict:
    """A composed field's value (its config object or dict form) as a dict of its settings."""
    if value is None:
        return {}
    if isinstance(value, Mapping):
        return dict(value)
    if hasattr(value, "to_dict"):
        return value.to_dict()
    return {f.name: getattr(value, f.name) for f in dataclasses.fields(value)
            if not (group == "llm" and f.name in LLM_NOT_SETTINGS)}


def upgrade_config(data: Mapping) -> dict:
    """A run's settings as written by any version (flat or composed) in this version's shape:
    renamed names (`RENAMED`) under their new names, derived ones (`DERIVED`) dropped, flat names
    of composed fields (`NESTED`) moved into them (a flat name wins over its field's value)."""
    out = dict(data)
    for old, new in RENAMED.items():
        if old in out and new not in out:
            out[new] = out.pop(old)
    for name in DERIVED:
        out.pop(name, None)
    for group in GROUPS:
        if group in out and not isinstance(out[group], Mapping):
            out[group] = group_dict(group, out[group])
    for flat, (group, name) in NESTED.items():
        if flat in out:
            out[group] = {**out.get(group, {}), name: out.pop(flat)}
    return out


def normalised_group(group: str, values: Mapping) -> dict:
    """A composed field's settings as its config holds them (`LLMSpec` names the model with the
    oracle's noise and an endpoint folded in, `ILLMConfig` parses the tasks)."""
    if group == "llm":
        from illm_tools.llm.spec import LLMSpec

        return group_dict(group, LLMSpec(**values))
    from illm_tools.intrinsic.illm_config import ILLMConfig

    return ILLMConfig(**values).to_dict()


def flat_settings(data: Mapping) -> dict:
    """A config's settings (`TrainConfig.to_dict()` or a config.json of any version) under their
    flat names (see the module docstring); its composed fields normalised by their configs (a bad
    value: one line, `UsageError`)."""
    out = upgrade_config(data)
    for group, names in GROUPS.items():
        values = normalised_group(group, out.pop(group, {}))
        out.update({flat: values[name] for flat, name in names.items()})
    return out


def flat_names(cls: type) -> list[str]:
    """Every setting of the config class `cls` (TrainConfig) by its flat name, in field order."""
    out = []
    for f in dataclasses.fields(cls):
        out += [flat for flat, (group, _) in NESTED.items() if group == f.name] if f.name in GROUPS else [f.name]
    return out


FLAGS = {"env_id": "--env", "run_dir": "--out", "obs_mode": "--mode", "total_steps": "--frames",
         "history_len": "--history", "model_dtype": "--dtype", "bonus_options": "--bonus-option",
         "network_options": "--network-option", "env_options": "--env-option", "task_weights": "--task-weight"}
"""The option of each setting whose flag is not `--` + its name (`illm train`'s documented flags)."""


def flag_of(name: str) -> str:
    """The option that sets the setting `name` ("--frames" for total_steps)."""
    return FLAGS.get(name, "--" + name.replace("_", "-"))


def write_config(run_dir: Path, config: dict) -> None:
    """Write run_dir/config.json atomically (temporary file, fsync, rename)."""
    durable.write_text(Path(run_dir) / CONFIG_NAME, json.dumps(config, indent=2))


def read_config(run_dir: Path) -> dict:
    """run_dir/config.json as written by `illm train`; one line when it is absent or damaged."""
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
