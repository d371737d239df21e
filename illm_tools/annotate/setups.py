"""The annotation setups a cache holds, read back as the options that select them, so that a run
(or a server) can adopt its cache's setup instead of having it typed again.

A setup is what every key of a run shares besides the state: the model as its backend serves it
(backend, model, dtype, quantisation, read back from the rows' fingerprints: `describe_model`), the
history length, the prompt layout (read back from a stored prompt, `layouts_of`, at this code's
template versions) and the renderer. A setup counts for a run when the cache holds entries of it
for every task the run reads and its renderer is the run's (the env's text renderer; in hop mode
a hop renderer, whose projection seed and beta come with it).

`illm train --cache DIR` with none of the model options (--backend, --model, --dtype, --quant,
--oracle-noise, --history, --layout, --hop-seed, --hop-beta) adopts the one setup the cache holds
for its tasks, and says so in one line; a cache holding several is refused, naming each with its
options; an empty one leaves the defaults. Live annotation then writes rows the cache's other users
read, whatever this machine's `--dtype auto` would have chosen. `illm serve --cache` does the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from illm_tools.errors import UsageError

ADOPTED = ("backend", "model", "model_dtype", "quant", "oracle_noise", "history_len", "layout", "hop_seed", "hop_beta")
"""The TrainConfig fields a run takes from its cache's setup (the CLI adopts when none was given)."""


@dataclass(frozen=True)
class Setup:
    """One setup of a cache, as options."""

    backend: str
    model: str
    dtype: str
    quant: str
    history_len: int
    layout: str
    renderer: str
    entries: int
    """Entries of the setup's least annotated task."""

    def options(self) -> str:
        """The flags that select it ("--backend oracle --history 0 --layout shared")."""
        from illm_tools.llm.backend import selecting_options

        model = selecting_options(self.backend, self.model, self.dtype, self.quant)
        hop = ""
        if self.renderer.startswith("hop@"):
            from illm_tools.tasks.setup import parse_hop_renderer

            settings = parse_hop_renderer(self.renderer)
            hop = f" --mode hop --hop-seed {settings['seed']} --hop-beta {settings['beta']:g}"
        return f"{model} --history {self.history_len} --layout {self.layout}{hop}"

    def fields(self) -> dict:
        """The TrainConfig fields of the setup (`ADOPTED`)."""
        out = {"backend": self.backend, "model": self.model, "model_dtype": self.dtype, "quant": self.quant,
               "oracle_noise": 0.0, "history_len": self.history_len, "layout": self.layout}
        if self.renderer.startswith("hop@"):
            from illm_tools.tasks.setup import parse_hop_renderer

            settings = parse_hop_renderer(self.renderer)
            out.update(hop_seed=settings["seed"], hop_beta=settings["beta"])
        return out


def cache_setups(cache, tasks: Sequence[str], renderer: str | None = None) -> list[Setup]:
    """The setups `cache` holds for every one of `tasks` (see the module docstring); `renderer`:
    the run's text renderer, or a hop renderer's "hop@" prefix for any hop setup (None: any)."""
    from illm_tools.llm.backend import describe_model
    from illm_tools.tasks.prompts import layouts_of
    from illm_tools.tasks.registry import get_task

    per_task: dict[tuple, dict[str, int]] = {}
    for row in cache.setups():
        task = row["task"]
        if task not in tasks:
            continue
        if renderer is not None and not (row["renderer"] == renderer or
                                         (renderer == "hop@" and row["renderer"].startswith("hop@"))):
            continue
        model = describe_model(row["model"], row["model_fingerprint"])
        if model is None:
            continue
        spec = get_task(task)
        for layout in layouts_of(task, row["prompt"]):
            if spec.templates[layout][1] != row["template_version"]:
                continue  # an older template of the layout: this code renders another prompt
            key = (model["backend"], model["model"], model["dtype"], model["quant"], int(row["history_len"]), layout,
                   row["renderer"])
            per_task.setdefault(key, {})[task] = per_task.get(key, {}).get(task, 0) + int(row["entries"])
    return sorted((Setup(*key, entries=min(counts.values())) for key, counts in per_task.items()
                   if set(counts) == set(tasks)), key=lambda s: -s.entries)


def adopt(cache, tasks: Sequence[str], renderer: str | None) -> Setup | None:
    """The one setup `cache` holds for `tasks`, or None when it holds none; several are refused in
    one line naming each."""
    setups = cache_setups(cache, tasks, renderer)
    if len(setups) > 1:
        listed = "; ".join(f"{s.options()} ({s.entries:,} entries)" for s in setups)
        raise UsageError(f"the cache {cache.root} holds {len(setups)} setups for the tasks {','.join(tasks)}: {listed}. "
                         "Pass the options of the one to train with")
    return setups[0] if setups else None


def adopt_model(cache) -> dict | None:
    """The one model setup (backend, model, dtype, quant) of the cache's rows, for `illm serve
    --cache` without model options; None for an empty cache; several are refused naming each."""
    from illm_tools.llm.backend import describe_model, selecting_options

    found: dict[tuple, tuple[dict, int]] = {}
    for row in cache.setups():
        model = describe_model(row["model"], row["model_fingerprint"])
        if model is not None:
            key = tuple(model.values())
            found[key] = (model, found.get(key, (model, 0))[1] + int(row["entries"]))
    if len(found) > 1:
        listed = "; ".join(f"{selecting_options(**m)} ({n:,} entries)" for m, n in found.values())
        raise UsageError(f"the cache {cache.root} holds annotations of {len(found)} model setups: {listed}. Pass the "
                         "options of the one to serve")
    return next(iter(found.values()))[0] if found else None

