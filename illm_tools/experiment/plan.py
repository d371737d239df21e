"""An `illm experiment`'s grid planned into runs (`plan`): each run's TrainConfig, folder and status,
all built before anything trains; `select` picks the runs `--only` names, `claim_results` the
results folder, and `unavailable_models` names the models a dry run would miss. A run's folder is
RESULTS/ENV/LABEL/seedN, so every grid value in a label is a bare name (`illm_tools.folders.bare_name`):
`cache: [data/a]` is refused, a bundle `{name: a, cache: data/a}` takes its place."""
from __future__ import annotations

import fnmatch
import itertools
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from illm_tools.errors import IllmError, UsageError
from illm_tools.experiment.spec import Spec
from illm_tools.folders import bare_name

SPEC_COPY = "spec.yaml"


@dataclass
class Run:
    """One run of the grid."""

    env_id: str
    label: str
    seed: int
    config: Any
    """Its `TrainConfig` (run_dir set)."""
    status: str = "new"
    """new | resume | done, from what its folder holds."""


def _apply(fields: dict, name: str, value: Any, spec: Spec, where: tuple) -> None:
    """Set a run setting (by its flat name, `illm_tools.rl.config.FLAT`: as `illm train`'s options name it; or
    env_options.KEY, or bonus_preset) in `fields`, refusing unknown names."""
    from illm_tools.rl.config import FLAT

    known = set(FLAT)
    if name.startswith("env_options."):
        fields.setdefault("env_options", {})[name.split(".", 1)[1]] = value
        return
    if name == "bonus_preset":  # a preset stands for its settings (`run_config` expands it), as in `illm train`
        from illm_tools.intrinsic.presets import preset_settings

        try:
            preset_settings(value)
        except UsageError as e:
            raise UsageError(f"{spec.line(*where)}: {e}") from None
        fields[name] = value
        return
    if name in ("env_id", "method", "seed", "run_dir", "total_steps", "resume"):
        raise UsageError(f"{spec.line(*where)}: {name} is set by the grid itself (envs, methods, seeds, frames, "
                         "the results folder): remove it")
    if name not in known:
        import difflib

        close = difflib.get_close_matches(name, sorted(known), n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise UsageError(f"{spec.line(*where)}: unknown setting {name!r}{hint}; settings are `illm train`'s "
                         "options by name (`illm train --help`) or env_options.KEY")
    fields[name] = value


def _label(method: str, combo: dict) -> str:
    return "-".join([method, *(f"{k.split('.')[-1]}={v['name'] if isinstance(v, dict) else v}"
                               for k, v in combo.items())])


def _combos(spec: Spec) -> list[tuple[dict, dict]]:
    """Every combination of grid values, each with where its names are written in the spec: the
    grid's alone, and for a method with a `method_grid`, the grid's crossed with its own (marked
    with the method, so that only its runs take them; `plan` drops the plain grid's combinations
    for that method)."""
    def product(grids: dict[str, tuple]) -> list[dict]:
        return [dict(zip(grids, values)) for values in itertools.product(*(g[1] for g in grids.values()))]

    plain = {k: (("grid",), v) for k, v in spec.grid.items()}
    out = []
    for combo in product(plain):
        out.append(({**combo, "__method__": None}, {k: plain[k][0] for k in combo}))
    for method, extra in spec.method_grid.items():
        grids = {**plain, **{k: (("method_grid", method), v) for k, v in extra.items()}}
        for combo in product(grids):
            out.append(({**combo, "__method__": method}, {k: grids[k][0] for k in combo}))
    return out


def plan(spec: Spec, results: str | Path, say: Callable[[str], None] | None = None) -> list[Run]:
    """Every run of the grid with its TrainConfig (all built now: a bad value is refused before
    anything runs) and its status from its folder; `say` hears each line `run_config` says (a cache's
    setup adopted) once."""
    said: set[str] = set()

    def once(line: str) -> None:
        if say is not None and line not in said:
            said.add(line)
            say(line)

    from illm_tools.envs import suite_of
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.rl.checkpoint import CHECKPOINT_NAME
    from illm_tools.rl.saved import read_run

    results = Path(results)
    for i, method in enumerate(spec.methods):
        try:
            get_method(method)
        except UsageError as e:
            raise UsageError(f"{spec.line('methods', i)}: {e}") from None
    for i, env_id in enumerate(spec.envs):
        try:
            suite_of(env_id)
        except IllmError as e:
            raise UsageError(f"{spec.line('envs', i)}: {e}") from None
    for key in ("method_settings", "method_grid"):
        for method in getattr(spec, key):
            if method not in spec.methods:
                raise UsageError(f"{spec.line(key, method)}: {key} names {method!r}, which is not among the spec's "
                                 f"methods ({', '.join(spec.methods)})")
    runs = []
    for env_id, method, (combo, where) in itertools.product(spec.envs, spec.methods, _combos(spec)):
        owner = combo["__method__"]  # None: the plain grid's, for the methods without a grid of their own
        if owner != method and (owner is not None or method in spec.method_grid):
            continue
        combo = {k: v for k, v in combo.items() if k != "__method__"}
        label = _label(method, combo)
        for name, value in combo.items():  # a plain value is part of its runs' folders (a bundle's name: `load_spec`)
            if not isinstance(value, dict):
                bare_name(f"{name.split('.')[-1]}={value}", f"{spec.line(*where[name], name)}: the grid value of {name}",
                          f"give it as a bundle with a plain name instead, e.g. {{name: a, {name}: {value}}}")
        base: dict = {}
        for name, value in spec.settings.items():
            _apply(base, name, value, spec, ("settings", name))
        for name, value in (spec.method_settings.get(method) or {}).items():
            _apply(base, name, value, spec, ("method_settings", method, name))
        for name, value in combo.items():
            if isinstance(value, dict):  # a bundle of settings, named by its `name`
                for key, setting in value.items():
                    if key != "name":
                        _apply(base, key, setting, spec, (*where[name], name))
            else:
                _apply(base, name, value, spec, (*where[name], name))
        for seed in spec.seeds:
            run_dir = results / env_id.replace("/", "-") / label / f"seed{seed}"
            settings = {**base, "env_id": env_id, "method": method, "seed": seed,
                        "total_steps": spec.env_frames.get(env_id, spec.frames), "run_dir": run_dir, "threads": 1}
            cfg = _run_config(settings, spec, f"{env_id} {label} seed {seed}", once)
            status = "new"
            if (run_dir / CHECKPOINT_NAME).exists():
                done = read_run(run_dir).frames
                status = "done" if done >= cfg.num_updates * cfg.batch_size else "resume"
                if status == "resume":  # its own settings from its folder, as `illm train --resume` reads them
                    cfg = _run_config({**settings, "resume": True}, spec, f"{env_id} {label} seed {seed}")
            runs.append(Run(env_id, label, seed, cfg, status))
    return runs


def _run_config(settings: dict, spec: Spec, run: str, say: Callable[[str], None] | None = None):
    """A grid run's TrainConfig, built as `illm train` builds one (`illm_tools.rl.build.run_config`:
    preset expanded, the cache's setup adopted, a resumed run's settings merged); refused in one line
    naming the run."""
    from illm_tools.rl.build import run_config

    try:
        return run_config(settings, say=say)
    except (IllmError, TypeError) as e:
        raise UsageError(f"{spec.line('settings')}: the run {run} is refused: {e}") from None


def select(runs: list[Run], only: list[str] | tuple = ()) -> list[Run]:
    """The runs that `--only`'s patterns pick (all of them without patterns): a pattern matches a run's
    label or its path ENV/LABEL/seedN. A pattern that picks no run is refused, naming the labels."""
    if not only:
        return list(runs)

    def picks(run: Run, pattern: str) -> bool:
        path = "/".join(Path(run.config.run_dir).parts[-3:])  # ENV/LABEL/seedN, as `plan` made it
        return fnmatch.fnmatchcase(run.label, pattern) or fnmatch.fnmatchcase(path, pattern)

    unmatched = [p for p in only if not any(picks(r, p) for r in runs)]
    if unmatched:
        labels = ", ".join(dict.fromkeys(r.label for r in runs))
        raise UsageError(f"--only {unmatched[0]!r} matches no run of this spec; its labels: {labels} "
                         "(or a path ENV/LABEL/seedN)")
    return [r for r in runs if any(picks(r, p) for p in only)]


def claim_results(spec: Spec, results: str | Path) -> Path:
    """Create the results folder with the spec copied in, or check that it holds this spec."""
    results = Path(results)
    copy = results / SPEC_COPY
    if copy.exists():
        if copy.read_text() != spec.text:
            raise UsageError(f"{results} holds the results of another spec ({copy} differs from {spec.path}): pass "
                             "another --out, or restore the spec that made them")
        return results
    if results.exists() and any(results.iterdir()):
        raise UsageError(f"{results} holds files but no {SPEC_COPY}: pass another --out for this experiment")
    results.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(spec.path, copy)
    return results


def unavailable_models(runs: list[Run]) -> dict[str, int]:
    """The model aliases the runs still to train would load that this machine cannot load offline
    (`illm models`), with how many runs each: a dry run names them before a grid fails on them."""
    from illm_tools.llm.backend import backend_class
    from illm_tools.llm.registry import list_models

    missing = {m.alias for m in list_models() if not m.available}
    out: dict[str, int] = {}
    for run in runs:
        cfg = run.config
        if (run.status != "done" and cfg.uses_llm and getattr(backend_class(cfg.llm.backend), "local_models", False)
                and cfg.llm.model in missing):
            out[cfg.llm.model] = out.get(cfg.llm.model, 0) + 1
    return out
