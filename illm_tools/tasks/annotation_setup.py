"""An annotation setup, in one place: what, besides the state and the model, decides an
annotation's keys (`AnnotationSetup`), how the setups a cache holds are read back as the options
that select them (`cache_setups`, `SetupOptions`), adopted by a run or a server that names none
(`adopt`, `adopt_model`) and checked against a run's own (`check_setup`).

`AnnotationSetup` is the env and its text renderer (or the hop translation's settings), the
language tasks, the history length and the template layout (each task's template version follows
from the layout). Its `builder` is the one place a `PromptBuilder` (the prompts and keys of one
env's states) is made: `illm annotate` and the live annotator (the `Annotator`'s builders), a
training run's targets, `illm serve`, `illm probe` and `illm data coverage` all build theirs
through it, for a model named by its spec and fingerprint hash (`builder_of(llm)`: an `LLMSpec`'s
`fingerprint()`, no weights loaded; a loaded backend's is hashed by the `Annotator` that holds it,
and a server compares requests with that one). A trainer sends the setup to a server as its
`wire()` form, which the server reads back with `from_wire` (one line naming what is wrong).

A cache's setups are what every key of a run shares besides the state: the model as its backend
serves it (backend, model, dtype, quantisation, read back from the rows' fingerprints:
`describe_model`), the history length, the prompt layout (read back from a stored prompt,
`layouts_of`, at this code's template versions) and the renderer (`AnnotationCache.setups` lists
the distinct ones; `setup_rows` each with the layouts its prompt fits, as `illm cache info` shows
them). A setup counts for a run when the cache holds entries of it for every task the
run reads and its renderer is the run's (the env's text renderer; in hop mode a hop renderer, whose
projection seed and beta come with it).

`illm train --cache DIR` with none of the model options (--backend, --model, --dtype, --quant,
--oracle-noise, --history, --layout, --hop-seed, --hop-beta) adopts the one setup the cache holds
for its tasks, and says so in one line; a cache holding several is refused, naming each with its
options; an empty one leaves the defaults. Live annotation then writes rows the cache's other users
read, whatever this machine's `--dtype auto` would have chosen. `illm serve --cache` does the same
for the model. A cache that holds annotations but none of a run's setup is refused by
`check_setup`, naming what differs.

A row's `model` is an identity, never where a request goes: a cache may come from anyone (`illm
cache import`), and the spec of a served model names an address and a key variable ("NAME@URL#VAR").
An adopted served model (openai) keeps only its served name; where it is reached and with which key
are the user's own options (`served.REACHED`: --endpoint, --api-key-env, --embed-endpoint) or the
default key variable, and without --endpoint its adoption is refused in one line (`served.reached_model`).
Nothing adopted is contacted before that, and the options a listing suggests name no address
(`--endpoint URL`).

The hop renderer's name lives here too: the renderer field of hop keys is the translation's
settings (`hop_renderer`), read back by `parse_hop_renderer`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from illm_tools.errors import CacheError, UsageError
from illm_tools.tasks.prompts import DEFAULT_TASKS, LAYOUTS, PromptBuilder, layouts_of
from illm_tools.tasks.registry import get_task, parse_tasks
from illm_tools.tasks.served import held_options, reached_model, served_addresses
HOP_VERSION = 2
"""Version of the hop record format and translation; part of every hop cache key (bump on change).
2: Crafter's pictures are grey-scaled before the translation (`Suite.hop_frame`)."""


def hop_renderer(seed: int, beta: float, window: int) -> str:
    """The `renderer` field of hop keys: the translation's settings (the model is in the key already)."""
    return f"hop@{HOP_VERSION}:seed={int(seed)}:beta={float(beta)!r}:window={int(window)}"


def parse_hop_renderer(renderer: str) -> dict | None:
    """{"seed", "beta", "window"} of a hop renderer string, None for a text renderer."""
    if not renderer.startswith("hop@"):
        return None
    fields = dict(part.split("=", 1) for part in renderer.split(":")[1:])
    return {"seed": int(fields["seed"]), "beta": float(fields["beta"]), "window": int(fields["window"])}


WIRE_FIELDS = ("env_id", "renderer", "history_len", "layout", "tasks")
"""The setup's fields in a live-annotation request (`illm serve`)."""


@dataclass(frozen=True)
class AnnotationSetup:
    """The key inputs an annotation shares besides the state and the model (module docstring)."""

    env_id: str
    """The env whose states are annotated (its game line opens every prompt)."""
    renderer: str
    """The env's text renderer (name@version), or a hop renderer (`hop_renderer`)."""
    tasks: tuple[str, ...] = DEFAULT_TASKS
    """The language tasks (`illm_tools.tasks.registry`)."""
    history_len: int = 3
    """Observation/action pairs of history in the prompts."""
    layout: str = "shared"
    """Template layout: shared or paper."""

    def __post_init__(self) -> None:
        for name in ("env_id", "renderer"):
            if not isinstance(getattr(self, name), str):
                raise UsageError(f"{name} must be a string, got {type(getattr(self, name)).__name__}")
        object.__setattr__(self, "tasks", parse_tasks(self.tasks, "tasks"))
        if self.layout not in LAYOUTS:
            raise UsageError(f"layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        if not isinstance(self.history_len, int) or isinstance(self.history_len, bool) or self.history_len < 0:
            raise UsageError(f"history_len must be a whole number >= 0, got {self.history_len!r}")
        if self.hop:
            try:
                parse_hop_renderer(self.renderer)
            except (KeyError, ValueError):
                raise UsageError(f"renderer {self.renderer!r} is not a hop renderer "
                                 "(hop@N:seed=..:beta=..:window=..)") from None

    @property
    def hop(self) -> bool:
        """Whether the states are hop windows (iLLM(hop)) rather than text."""
        return self.renderer.startswith("hop@")

    def builder(self, model: str, model_fingerprint: str) -> PromptBuilder:
        """The prompt builder of this setup for a model (its spec and fingerprint hash): the one
        place a `PromptBuilder` is made (module docstring)."""
        return PromptBuilder(env_id=self.env_id, renderer=self.renderer, model=model,
                             model_fingerprint=model_fingerprint, history_len=self.history_len, layout=self.layout)

    def builder_of(self, llm) -> PromptBuilder:
        """The prompt builder of this setup for an `LLMSpec` (placed): its model and `fingerprint()`,
        without loading weights."""
        return self.builder(llm.model, llm.fingerprint())

    def wire(self) -> dict:
        """The JSON fields of a live-annotation request (`WIRE_FIELDS`)."""
        return {"env_id": self.env_id, "renderer": self.renderer, "history_len": self.history_len,
                "layout": self.layout, "tasks": list(self.tasks)}

    @classmethod
    def from_wire(cls, body: dict) -> AnnotationSetup:
        """The setup of a request body (`wire()`'s fields); UsageError in one line when one is
        missing or wrong."""
        missing = [k for k in WIRE_FIELDS if k not in body]
        if missing:
            raise UsageError(f"the request lacks {', '.join(missing)}")
        return cls(**{k: body[k] for k in WIRE_FIELDS})


# ---- the setups a cache holds ------------------------------------------------------------------

def prompt_options(history_len: int, layout: str, hop: Mapping | None = None) -> str:
    """The flags that select prompt settings, the one place they are written: "--history 3 --layout
    shared", and a hop window's "--mode hop --hop-seed S --hop-beta B" (`hop`: its seed and beta)."""
    hops = f" --mode hop --hop-seed {hop['seed']} --hop-beta {hop['beta']:g}" if hop is not None else ""
    return f"--history {history_len} --layout {layout}{hops}"


def _model_options(model: str, fingerprint: str) -> str:
    """The options that select a cache row's model (`model_options`), a served model's address left
    for the user to give (`_options`)."""
    from illm_tools.llm.backend import describe_model, model_options

    found = describe_model(model, fingerprint)
    return held_options(**found) if found is not None else model_options(model, fingerprint)


@dataclass(frozen=True)
class SetupOptions:
    """One setup a cache holds, as the options that select it."""

    backend: str
    model: str
    dtype: str
    quant: str
    history_len: int
    layout: str
    renderer: str
    entries: int
    """Entries of the setup's least annotated task: the states answered for every task (a cache's
    entries are rows, one per state and task)."""
    model_fingerprint: str = ""
    """The model's identity: its fingerprint hash, as every key of the setup carries it."""
    served_at: tuple[str, ...] = ()
    """The model specs the rows were written under, most entries first (for a served model, the
    addresses its engine was reached at: one setup whatever the address, `model` the first)."""

    def options(self) -> str:
        """The flags that select it ("--backend oracle --history 0 --layout shared"; a served model's
        "--endpoint URL" left for the user to fill: `_options`)."""
        return f"{held_options(self.backend, self.model, self.dtype, self.quant)} {self.prompt_options()}"

    def prompt_options(self) -> str:
        """The flags that select its prompts ("--history 0 --layout shared", and hop's)."""
        return prompt_options(self.history_len, self.layout, parse_hop_renderer(self.renderer))

    def fields(self, reach: Mapping[str, str | None] | None = None, where=None) -> dict:
        """The TrainConfig fields of the setup (`illm_tools.rl.declared.ADOPTED`), its model reached where the user's `reach`
        options say (`reached_model`: a served model without --endpoint is refused; `where`: the cache)."""
        out = {"backend": self.backend, **reached_model(self.backend, self.model, reach or {}, where),
               "model_dtype": self.dtype, "quant": self.quant,
               "oracle_noise": 0.0, "history_len": self.history_len, "layout": self.layout}
        settings = parse_hop_renderer(self.renderer)
        if settings is not None:
            out.update(hop_seed=settings["seed"], hop_beta=settings["beta"])
        return out


def setup_rows(cache) -> list[dict]:
    """The setups an `AnnotationCache` holds as it lists them (`AnnotationCache.setups`: per task, the
    columns every key of a setup shares, its entries and one of its prompts), each with the template
    layouts its prompt fits (`layouts`: read back from the prompt, `layouts_of`), in the cache's order."""
    return [{**row, "layouts": layouts_of(row["task"], row["prompt"])} for row in cache.setups()]


def listed_setups(cache) -> list[dict]:
    """The setups an `AnnotationCache` holds as `illm cache info` lists them, one per task and model
    identity (its fingerprint: a served model reached at two addresses is one setup), each with its
    model's options, the addresses it was served at (openai: the engines' URLs) and its entries,
    by task and most entries first. Nothing is contacted and no model is loaded."""
    merged: dict[tuple, dict] = {}
    for u in setup_rows(cache):
        key = (u["task"], u["model_fingerprint"], u["history_len"], u["template_version"], u["renderer"],
               u["decoding"])
        seen = merged.get(key)
        if seen is None:
            merged[key] = seen = {**{k: u[k] for k in ("task", "model", "model_fingerprint", "history_len",
                                                      "template_version", "renderer", "decoding")},
                                  "entries": 0, "layouts": list(u["layouts"]), "specs": {}}
        seen["entries"] += int(u["entries"])
        seen["specs"][u["model"]] = seen["specs"].get(u["model"], 0) + int(u["entries"])
    out = []
    for seen in merged.values():
        specs = sorted(seen.pop("specs").items(), key=lambda kv: -kv[1])
        seen["model"] = specs[0][0]
        seen["model_options"] = _model_options(seen["model"], seen["model_fingerprint"])
        seen["served_at"] = served_addresses([m for m, _ in specs])
        out.append(seen)
    return sorted(out, key=lambda u: (u["task"], -u["entries"]))


def _open(cache):
    """`cache` as an `AnnotationCache` (given one, or its folder); None for a folder that holds no cache yet."""
    from illm_tools.cache.store import AnnotationCache

    if isinstance(cache, AnnotationCache):
        return cache
    return AnnotationCache(cache) if (Path(cache) / "manifest.json").is_file() else None


def cache_setups(cache, tasks: Sequence[str], renderer: str | None = None) -> list[SetupOptions]:
    """The setups `cache` (an `AnnotationCache` or its folder) holds for every one of `tasks` (see
    the module docstring), most entries first; `renderer`: the run's text renderer, or a hop
    renderer's "hop@" prefix for any hop setup (None: any)."""
    from illm_tools.llm.backend import describe_model

    cache = _open(cache)
    per_task: dict[tuple, dict[str, int]] = {}
    specs: dict[tuple, dict[str, int]] = {}  # the model strings of a setup (one per address it was served at)
    for row in setup_rows(cache) if cache is not None else []:
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
        for layout in row["layouts"]:
            if spec.templates[layout][1] != row["template_version"]:
                continue  # an older template of the layout: this code renders another prompt
            # the model's identity is its fingerprint, not the string it was named by (an engine's address)
            key = (model["backend"], row["model_fingerprint"], model["dtype"], model["quant"], int(row["history_len"]),
                   layout, row["renderer"])
            per_task.setdefault(key, {})[task] = per_task.get(key, {}).get(task, 0) + int(row["entries"])
            named = specs.setdefault(key, {})
            named[row["model"]] = named.get(row["model"], 0) + int(row["entries"])
    held = []
    for key, counts in per_task.items():
        if set(counts) != set(tasks):
            continue
        backend, fingerprint, dtype, quant, history, layout, renderer = key
        served = tuple(sorted(specs[key], key=lambda m: -specs[key][m]))
        held.append(SetupOptions(backend, served[0], dtype, quant, history, layout, renderer, entries=min(counts.values()),
                              model_fingerprint=fingerprint, served_at=served))
    return sorted(held, key=lambda s: -s.entries)


def adopt(cache, tasks: Sequence[str], renderer: str | None) -> SetupOptions | None:
    """The one setup `cache` (an `AnnotationCache`, or its folder) holds for `tasks`, or None when
    it holds none (or the folder holds no cache yet); several are refused in one line naming each."""
    setups = cache_setups(cache, tasks, renderer)
    if len(setups) > 1:
        listed = "; ".join(f"{s.options()} ({s.entries:,} states)" for s in setups)
        root = getattr(cache, "root", cache)
        raise UsageError(f"the cache {root} holds {len(setups)} setups for the tasks {','.join(tasks)}: {listed}. "
                         "Pass the options of the one to train with")
    return setups[0] if setups else None


def adopt_model(cache, reach: Mapping[str, str | None] | None = None) -> dict | None:
    """The one model setup of the cache's rows as `LLMSpec` fields (backend, model, dtype, quant, and
    the user's `reach` options: a served model is reached only where they say, `reached_model`), for
    `illm serve --cache` without model options; None for an empty cache; several are refused naming
    each."""
    from illm_tools.llm.backend import describe_model

    found: dict[tuple, tuple[dict, int]] = {}
    for row in cache.setups():
        model = describe_model(row["model"], row["model_fingerprint"])
        if model is not None:  # one model setup per fingerprint, whatever address its engine was reached at
            key = (model["backend"], row["model_fingerprint"], model["dtype"], model["quant"])
            found[key] = (found.get(key, (model, 0))[0], found.get(key, (model, 0))[1] + int(row["entries"]))
    if len(found) > 1:
        listed = "; ".join(f"{held_options(**m)} ({n:,} entries)" for m, n in found.values())
        raise UsageError(f"the cache {cache.root} holds annotations of {len(found)} model setups: {listed}. Pass the "
                         "options of the one to serve")
    if not found:
        return None
    model = next(iter(found.values()))[0]
    return {**model, **reached_model(model["backend"], model["model"], reach or {}, cache.root)}


_FLAGS = {"history_len": "--history", "layout": "--layout", "renderer": "renderer", "template_version": "template version",
          "decoding": "decoding"}


def _describe(setup: dict, fields: list[str], model: str | None) -> str:
    """The differing settings of a setup as the flags that select them."""
    return ", ".join((model or _model_options(setup["model"], setup["model_fingerprint"]))
                     if f == "model_fingerprint" else f"{_FLAGS[f]} {setup[f]}" for f in fields)


def check_setup(cache, builder: PromptBuilder, *, llm, tasks: Sequence[str] = ("action", "summary")) -> None:
    """Refuse a cache (an `AnnotationCache`) that holds annotations but none for this run's setup
    (`builder`'s), in one line naming the settings that differ and what the cache holds ("the cache
    holds --history 0 annotations; this run asks for --history 3"); `llm`: the run's placed
    `LLMSpec`. Nothing is refused when every task has entries of this setup."""
    held = setup_rows(cache)
    for task in tasks:
        want = builder.setup(task)
        rows = [r for r in held if r["task"] == task]

        def differs(r: dict) -> list[str]:
            out = [f for f in ("model_fingerprint", "history_len", "template_version", "renderer", "decoding")
                   if r[f] != want[f]]
            if want["layout"] not in r["layouts"]:  # each layout has its template versions: the layout says it
                return [f for f in out if f != "template_version"] + ["layout"]
            return out

        if any(not differs(r) for r in rows):
            continue
        if not rows:
            raise CacheError(f"the cache {cache.root} holds no {task} annotations, which this run needs: run "
                             f"`illm annotate DATA --cache {cache.root} --tasks {','.join(tasks)}`, or pass "
                             "--new-setup to let live annotation start them")
        closest = max(rows, key=lambda r: (-len(differs(r)), r["entries"]))
        fields = differs(closest)
        theirs = dict(closest, layout=closest["layouts"][0] if closest["layouts"] else "unknown")
        raise CacheError(
            f"the cache {cache.root} holds no {task} annotations for this run's setup: it holds "
            f"{_describe(theirs, fields, None)} annotations ({closest['entries']:,} entries); this run asks for "
            f"{_describe(want, fields, llm.options())}. Train with the "
            "cache's settings, or pass --new-setup to start this setup in the cache")
