"""The settings of a training run whose fields declare a fact (`illm_tools.settings.setting`), by their flat
names: the tables other code asks, derived from the fields, so that a setting's facts are written once,
where it is declared."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from illm_tools.errors import UsageError
from illm_tools.rl.config import PARTS, TrainConfig, flat_settings


def declared(fact: str, parts: Mapping[str, type] | None = None, own: type | None = None) -> frozenset[str]:
    """Flat names of the settings whose field declares `fact` (`setting(resumes=True)`): the run's own and
    its parts' (`parts`, `own`: TrainConfig's, unless a test plugs in others)."""
    parts, own = (PARTS if parts is None else parts), (TrainConfig if own is None else own)
    found = {f.name for f in dataclasses.fields(own) if f.name not in parts and f.metadata.get(fact)}
    found |= {f.metadata.get("flat", f.name) for cls in parts.values() for f in dataclasses.fields(cls)
              if f.metadata.get("run_setting", True) and f.metadata.get(fact)}
    return frozenset(found)


ADOPTED = declared("adopted")
"""Settings a run takes from its cache's one setup when none is given (`setting(adopted=True)`: the model's
and the prompt's; `illm_tools.rl.build.adopt_setup`)."""
RESUMABLE_CHANGES = declared("resumes")
"""Settings a resumed run may change (`setting(resumes=True)`): folder, devices, length, checkpoints, live
annotation; any other difference is refused (`check_resumable`)."""
AUTO_CHOICES = declared("auto")
"""Settings a run resolves when it starts that a resumed run keeps (`setting(auto=True)`: the LLM's dtype and
quantisation, the action space): their `auto`, given again on resume, is the choice the run made, not a change."""
MACHINE_CHOICES = declared("machine")
"""Settings a run resolves when it starts that a resumed run chooses again when they are not given and the
machine it resumes on lacks the recorded one (`setting(machine=True)`: the devices; a grid begun on a GPU
machine resumes on a CPU one: its recorded "cuda" would there refuse to start); a recorded device the machine
has is kept (runs put on the CPU of a GPU machine stay there). What the run learns does not depend on them."""
PRESET_FIELDS = declared("preset")
"""The settings a bonus preset names (`setting(preset=True)`; `illm_tools.intrinsic.presets`)."""


def check_resumable(state: dict, cfg, action_names: list[str]) -> None:
    """Refuse to resume a checkpoint (`state`, a saved run's) under other settings than it was
    trained with (but `RESUMABLE_CHANGES`) or another action list."""
    # compared under the flat names: a checkpoint of any version; a setting added after it was written counts at
    # its default value
    saved, now = flat_settings(state["config"]), cfg.flat()
    changed = sorted(k for k in now if saved.get(k) != now[k] and k not in RESUMABLE_CHANGES)
    if changed:
        raise UsageError(f"cannot resume with changed settings {changed}; "
                         "only total_steps and checkpointing may change")
    if state["action_names"] != list(action_names):
        raise UsageError(f"the checkpoint was trained with actions {state['action_names']}, "
                         f"the environment offers {list(action_names)}; use the same action space")
