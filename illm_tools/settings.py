"""`KEY=VALUE` settings from the command line (`--bonus-option`, `--network-option`,
`--env-option`), parsed in one place; the owner of each setting checks names and types."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from typing import Any

from illm_tools.errors import UsageError


def parse_pairs(values: Iterable[str] | None, option: str) -> dict[str, Any]:
    """Repeated KEY=VALUE strings as a dict; values that read as JSON numbers or booleans are
    converted (`num_dists=4`), the rest stay strings (the owner of the option checks them)."""
    out: dict[str, Any] = {}
    for value in values or []:
        key, sep, rest = value.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"{option} takes KEY=VALUE, got {value!r}")
        rest = rest.strip()
        try:
            parsed = json.loads(rest)
            out[key.strip()] = parsed if isinstance(parsed, (int, float, bool)) else rest
        except ValueError:
            out[key.strip()] = rest
    return out


INT_LIMIT = 2**62
"""The largest whole number a setting may hold (counts, seeds): past it numpy and torch overflow."""


def setting(default: Any = dataclasses.MISSING, *, flag: str | tuple[str, ...] | None = None,
            resumes: bool = False, adopted: bool = False, auto: bool = False, machine: bool = False,
            preset: bool = False, flat: str | None = None, run_setting: bool = True,
            factory: Any = dataclasses.MISSING, **field_options) -> Any:
    """A config field that declares, beside its default, the facts about it that other code asks, so
    that each is written once, where the setting is (`illm_tools.rl.declared` derives a training run's
    tables from them):

    - `flag`: the documented flag when it is not `--` + the field's name (`cli.options.dataclass_parameters`
      reads it; a string: kept beside the field's own flag; a tuple: the only flags, as `--mode` for
      obs_mode, whose own name means another thing);
    - `resumes`: a resumed training run may be given another value (its length, folder, devices,
      checkpointing, live annotation: `RESUMABLE_CHANGES`);
    - `adopted`: a training run takes it from its cache's one setup when no option that selects a setup
      is given (the model's and the prompt's: `ADOPTED`);
    - `auto`: its "auto" is resolved when a run starts and recorded; given again on resume, "auto" means
      the recorded choice, not a change (`AUTO_CHOICES`);
    - `machine`: a device the run resolves on the machine it starts on, chosen again on resume where the
      machine lacks the recorded one (`MACHINE_CHOICES`);
    - `preset`: a bonus preset names it (`--bonus-preset`: `PRESET_FIELDS`);
    - `flat`: a part's field's name among a run's settings where the run has a setting of the field's
      own name (the LLM's `dtype` is a run's `model_dtype`);
    - `run_setting`: False for a field that is no setting of a training run (the LLM's `offline`)."""
    metadata = {k: v for k, v in (("flag", flag), ("flat", flat)) if v is not None}
    metadata |= {k: True for k, v in (("resumes", resumes), ("adopted", adopted), ("auto", auto),
                                      ("machine", machine), ("preset", preset)) if v}
    metadata |= {} if run_setting else {"run_setting": False}
    return dataclasses.field(default=default, default_factory=factory, metadata=metadata, **field_options)


def declared_flag(cls: Any, name: str) -> str | None:
    """The flag the field `name` of the dataclass `cls` declares (`setting(flag=...)`), its first
    where it declares several; None where it declares none."""
    fields = getattr(cls, "__dataclass_fields__", {})
    flag = fields[name].metadata.get("flag") if name in fields else None
    return flag[0] if isinstance(flag, tuple) else flag


def flag_of(name: str, cls: Any = None) -> str:
    """The option that sets the field `name` (of the config class `cls`, when it declares one)."""
    return (declared_flag(cls, name) if cls is not None else None) or "--" + name.replace("_", "-")


def check_numbers(config: Any, *, positive: Iterable[str] = (), non_negative: Iterable[str] = (),
                  unit: Iterable[str] = (), flags: dict[str, str] | None = None) -> None:
    """Refuse in one line a setting of `config` (a dataclass) that is not a finite number in its
    range: `positive` (> 0), `non_negative` (>= 0), `unit` ([0, 1]); None is left alone (an unset
    optional). Every whole number must also fit `INT_LIMIT`. An option is named by the flag its field
    declares (`setting(flag=...)`), or by `flags` (`{"total_steps": "--frames"}`)."""
    import math

    flags = flags or {}
    for kind, names in (("positive", positive), ("non_negative", non_negative), ("unit", unit)):
        for name in names:
            value = getattr(config, name)
            if value is None:
                continue
            flag = flags.get(name) or flag_of(name, type(config))
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    (isinstance(value, float) and not math.isfinite(value)):
                raise UsageError(f"{flag} must be a finite number, got {value!r}")
            if isinstance(value, int) and abs(value) > INT_LIMIT:
                raise UsageError(f"{flag} is too large: {value:,} (at most {INT_LIMIT:,})")
            if (kind == "positive" and value <= 0) or (kind == "non_negative" and value < 0) or \
                    (kind == "unit" and not 0 <= value <= 1):
                want = {"positive": "positive", "non_negative": "0 or more", "unit": "between 0 and 1"}[kind]
                raise UsageError(f"{flag} must be {want}, got {value}")


def check_folder(path: Any, flag: str) -> None:
    """Refuse a path a command would write a folder at when a file is there, or above it."""
    from pathlib import Path

    if path is None:
        return
    if Path(path).exists() and not Path(path).is_dir():
        raise UsageError(f"{flag} {path} is a file: pass a folder")
    above = next((p for p in Path(path).parents if p.exists()), None)  # a file on the way: it cannot be made
    if above is not None and not above.is_dir():
        raise UsageError(f"{flag} {path} lies under {above}, a file: pass a folder elsewhere")


def check_new_file(path: Any, flag: str) -> None:
    """Refuse a path a command would write a new file at: a folder there, a file above it, or a file
    already there (nothing is overwritten unless asked: pass another path)."""
    from pathlib import Path

    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise UsageError(f"{flag} {path} is a folder: pass a file name (e.g. {path / 'figures.json'})")
    if path.exists():
        raise UsageError(f"{flag} {path} exists and would be overwritten: pass another file, or remove it first")
    above = next((p for p in path.parents if p.exists()), None)
    if above is not None and not above.is_dir():
        raise UsageError(f"{flag} {path} lies under {above}, a file: pass a path elsewhere")
