"""A run's `TrainConfig` from what was given: the one place that expands a bonus preset, merges a
resumed run's own settings and adopts the cache's annotation setup. `illm train` (its options)
and `illm experiment` (a spec's grid) both build their runs here, so that the same settings train
the same thing whichever way they came.

Settings are given under their flat names (`TrainConfig.flat`: the options' names, as specs and
older config.json files name them: model, model_dtype, lambda_a, ...), with `bonus_preset` for a
preset, already typed (dict settings parsed, paths as paths or strings).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from pathlib import Path
from typing import Any

from illm_tools.errors import UsageError
from illm_tools.rl.config import TrainConfig, flag_of
from illm_tools.intrinsic.presets import bonus_weights
from illm_tools.rl.declared import ADOPTED, AUTO_CHOICES, MACHINE_CHOICES, PRESET_FIELDS, RESUMABLE_CHANGES

def _missing_here(device) -> bool:
    """Whether `device` names a CUDA device this machine does not have."""
    import torch

    if not isinstance(device, str) or not device.startswith("cuda"):
        return False
    index = int(device[5:]) if ":" in device else 0
    return index >= (torch.cuda.device_count() if torch.cuda.is_available() else 0)


def run_config(settings: Mapping[str, Any], given: Collection[str] | None = None, *,
               say: Callable[[str], None] | None = None) -> TrainConfig:
    """The run's TrainConfig from `settings` (flat names; unset ones take their defaults):

    - `bonus_preset` (or, without one, the method's own preset, `Method.preset`) gives every
      PRESET_FIELDS setting not given (a None value counts as not given);
    - with `resume`, the run folder's config.json gives every setting, and of `given` (the names
      the user set: default all of `settings`) those a resumed run may change (RESUMABLE_CHANGES)
      apply; any other given setting that differs from the run's is refused in one line naming it;
    - else, when the run reads LLM targets from a cache that holds annotations and none of the
      options that select a setup (`ADOPTED`) was given, it takes the cache's setup, saying so
      through `say` (`adopt_setup`); where a served model is reached (`REACHED`: --endpoint,
      --api-key-env, --embed-endpoint) is never taken from the cache, only from these settings.
    """
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.tasks.served import REACHED

    settings = dict(settings)
    given = set(settings) if given is None else set(given)
    preset = settings.pop("bonus_preset", None)
    if preset is not None:
        given |= set(PRESET_FIELDS)  # a preset stands for its settings
    method = get_method(settings.get("method", TrainConfig.__dataclass_fields__["method"].default))
    weights = bonus_weights(preset or method.preset, **{w: settings.pop(w, None) for w in PRESET_FIELDS})
    settings.update(weights)
    if settings.get("resume"):
        return resumed(Path(settings["run_dir"]), settings, given - {"resume", "run_dir"})
    reach = {}
    if not given & set(ADOPTED):  # a setup may be adopted: the user's --endpoint reaches its model, set after
        reach = {k: settings.pop(k) for k in REACHED if settings.get(k)}
    return adopt_setup(TrainConfig.from_dict(settings), given, say, reach)


def resumed(run_dir: Path, settings: Mapping[str, Any], given: Collection[str]) -> TrainConfig:
    """The TrainConfig of a resumed run: its own settings from its config.json, with the `given`
    ones of `settings` applied where a resumed run may change them (RESUMABLE_CHANGES: --frames,
    --live-budget, threads, ...; the folder may have moved) and its devices chosen again where not
    given and this machine lacks them (MACHINE_CHOICES). Any other given setting that differs
    from the run's is refused in one line naming its option."""
    from illm_tools.rl.saved import read_run

    own = {**read_run(run_dir).settings, "run_dir": str(run_dir), "resume": True}  # the folder may have moved
    stored = TrainConfig.from_dict(own).flat()
    unset = TrainConfig().flat()
    changes = {**{k: unset[k] for k in MACHINE_CHOICES if k not in given and _missing_here(stored.get(k))},
               **{k: settings[k] for k in given if k in settings
                  and not (k in AUTO_CHOICES and settings[k] in ("auto", None))}}
    cfg = TrainConfig.from_dict({**stored, **changes})
    now = cfg.flat()  # compared as the config holds them ("1" and [1] alike, the LLM named one way)
    refused = sorted(f"{flag_of(k)} (the run has {stored.get(k)!r})" for k, v in now.items()
                     if stored.get(k) != v and k not in RESUMABLE_CHANGES)
    if refused:
        allowed = sorted(flag_of(k) for k in RESUMABLE_CHANGES if k != "resume")
        raise UsageError(f"--resume continues {run_dir} with its own settings, and {', '.join(refused)} would "
                         f"change what it learns: leave {'them' if len(refused) > 1 else 'it'} out, or train into a "
                         f"new --out (a resumed run may change {', '.join(allowed)})")
    return cfg


def adopt_setup(cfg: TrainConfig, given: Collection[str], say: Callable[[str], None] | None = None,
                reach: Mapping[str, str] | None = None) -> TrainConfig:
    """`cfg` with its cache's annotation setup adopted (`illm_tools.tasks.annotation_setup.adopt`) when the run
    reads targets from a cache holding annotations and none of the setup's options was `given`;
    `say` hears which, in one line. `reach`: the user's own --endpoint, --api-key-env and
    --embed-endpoint, set on the model either way: an adopted served model is reached only there (a
    cache's rows never say where a request goes; without --endpoint it is refused in one line)."""
    from illm_tools.tasks.annotation_setup import adopt

    reach = dict(reach or {})

    def own() -> TrainConfig:  # nothing adopted: the run's model with the options as given
        return TrainConfig.from_dict({**cfg.flat(), **reach}) if reach else cfg

    if not cfg.needs_targets or cfg.targets.cache is None or set(given) & set(ADOPTED) or \
            not (cfg.targets.cache / "manifest.json").is_file():
        return own()
    from illm_tools.cache.store import AnnotationCache

    renderer = "hop@" if cfg.setup.hop else cfg.annotation_setup.renderer
    setup = adopt(AnnotationCache(cfg.targets.cache), cfg.target_tasks, renderer)
    if setup is None:
        return own()
    adopted = TrainConfig.from_dict({**cfg.flat(), **setup.fields(reach, cfg.targets.cache)})
    if say is not None:
        say(f"adopting the cache's setup: {adopted.llm.options()} {setup.prompt_options()} ({setup.entries:,} states "
            "answered for every task; give any of these options to choose another)")
    return adopted
