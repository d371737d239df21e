"""`illm experiment SPEC.yaml`: a grid of training runs (methods x envs x settings x seeds) under one
results folder, run N at a time, finished runs skipped and unfinished ones resumed.

A spec (YAML; experiments/specs/ holds the paper's tables at CPU budgets):

    name: table1-distractors
    frames: 50000                 # per run (the paper: 100M; `--frames` overrides, env_frames too)
    env_frames:                   # per env, over `frames` (a level that needs more)
      BabyAI-GoToLocal-v0: 60000
    seeds: [0, 1, 2]              # or a count: 3 (`--seeds` overrides)
    envs: [BabyAI-GoToLocal-v0]
    methods: [ppo, rnd, illm]
    grid:                         # every combination of these values (TrainConfig fields, or
      num_dists: [4, 8, 16]       # env_options.KEY for an env option)
    method_grid:                  # per method, more values crossed with `grid` (e.g. the oracle's
      illm: {oracle_noise: [0, 0.5, 1]}   # quality for illm alone)
    settings:                     # for every run (TrainConfig fields)
      num_envs: 16
    method_settings:              # per method, over `settings`
      illm: {cache: data/ann, history_len: 0, live_budget: 16}
    paper:                        # what the paper sets (not run; checked by the test suite): its
      source: Table 1             # rows, grid values, frames and seeds, and `differs`: each setting
      methods: [rnd, illm]        # this spec sets otherwise, with the reason
      grid: {num_dists: [4, 8, 16]}
      frames: 100000000
      seeds: 10
      differs: {frames: "a CPU budget", seeds: "a CPU budget"}

A grid value may be a mapping: a bundle of settings applied together, named by its `name` key (the
label's value), e.g. `annotator: [{name: oracle, backend: oracle}, {name: gpt2, model: gpt2}]`.

Everything is checked before anything runs: the top-level keys, the method names, the env ids, the
setting names (each a field of `illm_tools.rl.config.TrainConfig`, or `env_options.<name>`, which
its suite checks) and their values (every run's TrainConfig is built); a bad one is refused in one
line naming the spec's line. A run's folder is RESULTS/<env>/<label>/seed<n> (the label: the method
and the grid values, e.g. `illm-num_dists=8`); the spec is copied to RESULTS/spec.yaml, and a
results folder made from another spec is refused (grids never mix). A run whose checkpoint has
reached its frames is skipped, one with a checkpoint short of them is resumed (`--resume`), the
rest start; runs go `jobs` at a time, each in a process of its own with one torch thread.
`--only PATTERN` (repeatable) trains a part of the grid: the runs whose label (`ppo`,
`illm-annotator=student`) or path under the results folder (`BabyAI-GoToLocal-v0/ppo/seed0`) a
pattern matches (shell wildcards); the rest are left as they are, for a later call.
"""
from __future__ import annotations

import dataclasses
import fnmatch
import itertools
import shutil
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from illm_tools.errors import IllmError, UsageError

TOP_KEYS = ("name", "frames", "env_frames", "seeds", "envs", "methods", "grid", "method_grid", "settings",
            "method_settings", "description", "paper", "cluster")
LAUNCHERS = ("local", "slurm", "submitit-local")
"""How runs start: local (`--jobs` processes here), slurm (a job each through submitit, one array),
submitit-local (submitit's local executor: the slurm path on this machine, for trying it)."""


@dataclass(frozen=True)
class Cluster:
    """Resources of one run's job under a scheduler: a spec's `cluster:` block, which the CLI's
    --partition, --time-minutes, --cpus, --gpus and --mem-gb override."""
    partition: str | None = None
    time_minutes: int = 240
    cpus: int = 1
    gpus: int = 0
    mem_gb: float | None = None

    def merged(self, **overrides: Any) -> Cluster:
        """These settings with every override that is not None, checked."""
        from illm_tools.settings import check_numbers

        out = replace(self, **{k: v for k, v in overrides.items() if v is not None})
        check_numbers(out, positive=("time_minutes", "cpus", "mem_gb"), non_negative=("gpus",))
        return out


CLUSTER_KEYS = tuple(f.name for f in fields(Cluster))
REQUIRED = ("envs", "methods")
SPEC_COPY = "spec.yaml"


@dataclass
class ExperimentConfig:
    """An `illm experiment`: the spec, where its results go, and how its runs are started."""

    spec: Path
    """The experiment's YAML spec (experiments/specs/ has the paper's tables)."""
    out: Path | None = None
    """Results folder (default: results/<spec name>)."""
    jobs: int = 1
    """Runs trained at a time, each in its own process with one thread."""
    frames: int | None = None
    """Frames per run, over the spec's (the paper: 100000000)."""
    seeds: int | None = None
    """Seeds 0..N-1, over the spec's (the paper: 10)."""
    dry_run: bool = False
    """Check the spec and list the runs; train nothing."""
    launcher: str = "local"
    """How runs start: local (--jobs processes here), slurm (one job array through submitit, --jobs tasks at a
    time), submitit-local (the slurm path on this machine, to try it)."""
    partition: str | None = None
    """SLURM partition (over the spec's cluster: block)."""
    time_minutes: int | None = None
    """Time limit of one run's job (default 240)."""
    cpus: int | None = None
    """CPUs of one run's job, its torch threads (default 1)."""
    gpus: int | None = None
    """GPUs of one run's job (default 0)."""
    mem_gb: float | None = None
    """Memory of one run's job in GB (default: the partition's)."""
    only: list[str] = field(default_factory=list)
    """Train only the runs whose label or path a pattern matches (repeatable, shell wildcards), e.g.
    --only ppo --only 'illm-annotator=*' or --only '*/seed0'; the others wait for a later call."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers

        self.spec = Path(self.spec)
        self.out = Path(self.out) if self.out is not None else None
        check_numbers(self, positive=("jobs", "frames", "seeds"))  # the cluster's: `Cluster.merged` in `load`
        check_folder(self.out, "--out")
        check_launcher(self.launcher)

    def load(self) -> tuple[Spec, Cluster, Path]:
        """The spec with --frames and --seeds applied, its cluster settings with the options over
        them, and the results folder."""
        spec = load_spec(self.spec, frames=self.frames, seeds=self.seeds)
        cluster = spec.cluster.merged(partition=self.partition, time_minutes=self.time_minutes, cpus=self.cpus,
                                      gpus=self.gpus, mem_gb=self.mem_gb)
        return spec, cluster, self.out or Path("results") / spec.name


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


@dataclass
class Spec:
    name: str
    path: Path
    text: str
    frames: int
    seeds: list[int]
    envs: list[str]
    methods: list[str]
    env_frames: dict[str, int] = field(default_factory=dict)
    """Per env, frames per run over `frames`."""
    grid: dict[str, list] = field(default_factory=dict)
    method_grid: dict[str, dict[str, list]] = field(default_factory=dict)
    """Per method, more grid values crossed with `grid` for that method's runs alone."""
    settings: dict[str, Any] = field(default_factory=dict)
    method_settings: dict[str, dict] = field(default_factory=dict)
    paper: dict = field(default_factory=dict)
    """What the paper sets for this table (documentation, checked by tests/test_experiment.py)."""
    cluster: Cluster = field(default_factory=Cluster)
    """Resources of a run's job under a scheduler."""
    lines: dict[tuple, int] = field(default_factory=dict)
    """(key, subkey, ...) -> line number in the file, for errors."""

    def line(self, *path) -> str:
        for n in range(len(path), 0, -1):
            if path[:n] in self.lines:
                return f"{self.path} line {self.lines[path[:n]]}"
        return str(self.path)


def _lines(node, prefix: tuple = ()) -> dict[tuple, int]:
    """The line of every mapping key (and list item) of a composed YAML node, by its key path."""
    import yaml

    out: dict[tuple, int] = {}
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            path = (*prefix, key.value)
            out[path] = key.start_mark.line + 1
            out.update(_lines(value, path))
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            out[(*prefix, i)] = item.start_mark.line + 1
            out.update(_lines(item, (*prefix, i)))
    return out


def load_spec(path: str | Path, *, frames: int | None = None, seeds: int | list[int] | None = None) -> Spec:
    """Read and check a spec file's shape (names and values are checked by `plan`)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise UsageError(f"no experiment spec at {path}: pass a YAML file (experiments/specs/ has examples)")
    text = path.read_text()
    try:
        data = yaml.safe_load(text)
        lines = _lines(yaml.compose(text)) if data else {}
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise UsageError(f"{path}{where} is not valid YAML ({getattr(e, 'problem', e)}): fix the spec") from None
    if not isinstance(data, dict):
        raise UsageError(f"{path} must be a mapping with keys {', '.join(REQUIRED)} (and "
                         f"{', '.join(k for k in TOP_KEYS if k not in REQUIRED)})")
    spec_lines = lines
    for key in data:
        if key not in TOP_KEYS:
            import difflib

            close = difflib.get_close_matches(str(key), TOP_KEYS, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise UsageError(f"{path} line {spec_lines.get((key,), '?')}: unknown key {key!r}{hint}; a spec takes "
                             f"{', '.join(TOP_KEYS)}")
    for key in REQUIRED:
        if not data.get(key):
            raise UsageError(f"{path}: the spec needs a non-empty {key!r} list")

    def as_list(key: str) -> list:
        value = data[key]
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list):
            raise UsageError(f"{path} line {spec_lines.get((key,), '?')}: {key} must be a list")
        return value

    chosen_seeds = seeds if seeds is not None else data.get("seeds", 3)
    seed_list = list(range(chosen_seeds)) if isinstance(chosen_seeds, int) else list(chosen_seeds)
    if not seed_list or not all(isinstance(s, int) and s >= 0 for s in seed_list):
        raise UsageError(f"{path} line {spec_lines.get(('seeds',), '?')}: seeds must be a count or a list of "
                         "non-negative integers")
    grid = data.get("grid") or {}
    method_grid = data.get("method_grid") or {}
    settings = data.get("settings") or {}
    per_method = data.get("method_settings") or {}
    for key, value in (("grid", grid), ("method_grid", method_grid), ("settings", settings),
                       ("method_settings", per_method)):
        if not isinstance(value, dict):
            raise UsageError(f"{path} line {spec_lines.get((key,), '?')}: {key} must be a mapping")
    grids = [(("grid",), grid)] + [(("method_grid", m), g) for m, g in method_grid.items()]
    for where, values_of in grids:
        if not isinstance(values_of, dict):
            raise UsageError(f"{path} line {spec_lines.get(where, '?')}: {'.'.join(where)} must be a mapping of "
                             "setting -> list of values")
        for key, values in values_of.items():
            if not isinstance(values, list) or not values:
                raise UsageError(f"{path} line {spec_lines.get((*where, key), '?')}: {'.'.join(where)}.{key} must be "
                                 "a non-empty list of values")
            for value in values:
                if isinstance(value, dict) and not value.get("name"):
                    raise UsageError(f"{path} line {spec_lines.get((*where, key), '?')}: a bundle of settings in "
                                     f"{'.'.join(where)}.{key} needs a name (its label), e.g. {{name: oracle, backend: "
                                     "oracle}")
    cluster = data.get("cluster") or {}
    if not isinstance(cluster, dict) or set(cluster) - set(CLUSTER_KEYS):
        bad = sorted(set(cluster) - set(CLUSTER_KEYS)) if isinstance(cluster, dict) else []
        line = spec_lines.get(("cluster", *bad[:1]), spec_lines.get(("cluster",), "?"))
        raise UsageError(f"{path} line {line}: cluster takes {', '.join(CLUSTER_KEYS)}")
    try:
        cluster = Cluster().merged(**cluster)
    except UsageError as e:
        raise UsageError(f"{path} line {spec_lines.get(('cluster',), '?')}: cluster: {e}") from None
    paper = data.get("paper")
    if paper is not None and not isinstance(paper, dict):
        raise UsageError(f"{path} line {spec_lines.get(('paper',), '?')}: paper must be a mapping (what the paper "
                         "sets: source, methods, grid, frames, seeds, differs)")
    total = frames if frames is not None else data.get("frames", 50_000)
    if not isinstance(total, int) or total <= 0:
        raise UsageError(f"{path} line {spec_lines.get(('frames',), '?')}: frames must be a positive integer")
    envs = [str(e) for e in as_list("envs")]
    env_frames = {} if frames is not None else (data.get("env_frames") or {})
    if not isinstance(env_frames, dict):
        raise UsageError(f"{path} line {spec_lines.get(('env_frames',), '?')}: env_frames must be a mapping of env id "
                         "-> frames")
    for env_id, count in env_frames.items():
        where = f"{path} line {spec_lines.get(('env_frames', env_id), '?')}"
        if env_id not in envs:
            raise UsageError(f"{where}: env_frames names {env_id!r}, which is not among the spec's envs")
        if not isinstance(count, int) or isinstance(count, bool) or count <= 0:
            raise UsageError(f"{where}: env_frames.{env_id} must be a positive integer, got {count!r}")
    return Spec(name=str(data.get("name") or path.stem), path=path, text=text, frames=total, seeds=seed_list,
                env_frames={str(k): int(v) for k, v in env_frames.items()},
                envs=envs, methods=[str(m) for m in as_list("methods")], grid=grid,
                method_grid=method_grid, settings=settings, method_settings=per_method, paper=paper or {},
                cluster=cluster, lines=spec_lines)


def _apply(fields: dict, name: str, value: Any, spec: Spec, where: tuple) -> None:
    """Set a TrainConfig field (or env_options.KEY, or bonus_preset) in `fields`, refusing unknown names."""
    from illm_tools.rl.config import TrainConfig

    known = {f.name for f in dataclasses.fields(TrainConfig)}
    if name.startswith("env_options."):
        fields.setdefault("env_options", {})[name.split(".", 1)[1]] = value
        return
    if name == "bonus_preset":  # a preset stands for its settings (`bonus_weights`, below), as in `illm train`
        from illm_tools.rl.config import bonus_weights

        try:
            bonus_weights(value)
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
        raise UsageError(f"{spec.line(*where)}: unknown setting {name!r}{hint}; settings are TrainConfig fields "
                         "(`illm train --help`) or env_options.KEY")
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


def plan(spec: Spec, results: str | Path) -> list[Run]:
    """Every run of the grid with its TrainConfig (all built now: a bad value is refused before
    anything runs) and its status from its folder."""
    from illm_tools.envs import suite_of
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.rl.checkpoint import CHECKPOINT_NAME, load_checkpoint
    from illm_tools.rl.config import PRESET_FIELDS, TrainConfig, bonus_weights

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
        weights = bonus_weights(base.pop("bonus_preset", None) or get_method(method).preset,
                                **{w: base.pop(w, None) for w in PRESET_FIELDS})
        for seed in spec.seeds:
            run_dir = results / env_id.replace("/", "-") / label / f"seed{seed}"
            try:
                cfg = TrainConfig(**{**base, **weights, "env_id": env_id, "method": method, "seed": seed,
                                     "total_steps": spec.env_frames.get(env_id, spec.frames), "run_dir": run_dir,
                                     "threads": 1})
            except (IllmError, TypeError) as e:
                raise UsageError(f"{spec.line('settings')}: the run {env_id} {label} seed {seed} is refused: "
                                 f"{e}") from None
            status = "new"
            if (run_dir / CHECKPOINT_NAME).exists():
                done = int(load_checkpoint(run_dir)["global_step"])
                status = "done" if done >= cfg.num_updates * cfg.batch_size else "resume"
                cfg = dataclasses.replace(cfg, resume=status == "resume")
            runs.append(Run(env_id, label, seed, cfg, status))
    return runs


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


_STOP = None  # a local grid worker's copy of the grid's stop event (`_init_worker`)
POLL_S = 0.5  # how often the local grid's parent checks `should_stop` while runs train


def _init_worker(stop) -> None:
    """A local grid worker. Ctrl-C reaches the whole process group; the worker ignores it and the
    parent alone decides: it sets `stop`, which every run reads after each update (a checkpoint,
    then an early return), so no update is cut in half and no worker prints a traceback."""
    import signal

    global _STOP
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _STOP = stop


def _train_one(cfg) -> dict:
    """One run in a worker process (its metrics' last line; `stopped` when the grid's stop ended it
    early with a checkpoint)."""
    import os

    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from illm_tools.rl.run import train

    return train(cfg, should_stop=_STOP.is_set if _STOP is not None else None)


def _outcome(run: Run, future: Future) -> str:
    """A finished future's (or submitit job's) run status set, and the event `on_run` hears: "done",
    "failed: <reason>", "stopped at N frames (checkpoint written)", or, stopped before its first
    update (the trainer writes no checkpoint then), "stopped before its first update" (status "new")."""
    try:
        result = future.result()
    except Exception as e:  # noqa: BLE001 - one failed run must not stop the grid; it is reported
        run.status = "failed"
        return _failure(e)
    if not result.get("stopped"):
        run.status = "done"
        return "done"
    if not result.get("global_step"):
        run.status = "new"
        return "stopped before its first update"
    run.status = "stopped"
    return f"stopped at {result['global_step']:,} frames (checkpoint written)"


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
    from illm_tools.llm.registry import list_models

    missing = {m.alias for m in list_models() if not m.available}
    out: dict[str, int] = {}
    for run in runs:
        cfg = run.config
        if run.status != "done" and (cfg.needs_targets or cfg.obs_mode == "hop") and cfg.backend == "transformers" \
                and cfg.llm_model in missing:
            out[cfg.llm_model] = out.get(cfg.llm_model, 0) + 1
    return out


def check_launcher(launcher: str) -> None:
    if launcher not in LAUNCHERS:
        raise UsageError(f"--launcher must be one of {', '.join(LAUNCHERS)}, got {launcher!r}")


def _failure(e: BaseException) -> str:
    """A failed run's reason in one line."""
    return f"failed: {str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__}"


def _submitit(spec: Spec, results: Path, todo: list[Run], jobs: int, launcher: str, cluster: Cluster,
              on_run: Callable[[Run, str], None] | None) -> None:
    """Each run a job through submitit (a SLURM job array, `jobs` of its tasks at a time; or
    submitit's local executor in waves of `jobs` processes, to try the path without a cluster).
    The jobs' logs go to RESULTS/.submitit/<job id>. Waits for every job: stopping this command
    leaves queued jobs running (`scancel` them), and a job whose run another job is training
    stops at once (the run folder's lock)."""
    try:
        import submitit
    except ImportError:
        raise UsageError(f"--launcher {launcher} needs the package submitit: pip install submitit") from None
    executor = submitit.AutoExecutor(folder=str(results / ".submitit" / "%j"),
                                     cluster="slurm" if launcher == "slurm" else "local")
    params: dict[str, Any] = {"name": f"illm-{spec.name}", "timeout_min": cluster.time_minutes,
                              "cpus_per_task": cluster.cpus}
    if cluster.gpus:
        params["gpus_per_node"] = cluster.gpus
    if cluster.mem_gb:
        params["mem_gb"] = cluster.mem_gb
    if launcher == "slurm":
        params["slurm_array_parallelism"] = jobs
        if cluster.partition:
            params["slurm_partition"] = cluster.partition
    executor.update_parameters(**params)
    configs = [replace(r.config, threads=cluster.cpus) for r in todo]
    waves = [range(len(todo))] if launcher == "slurm" else [range(i, min(i + jobs, len(todo)))
                                                             for i in range(0, len(todo), jobs)]
    for wave in waves:
        submitted = executor.map_array(_train_one, [configs[i] for i in wave])
        for i, job in zip(wave, submitted):
            event = _outcome(todo[i], job)
            if on_run is not None:
                on_run(todo[i], event)


def run_experiment(spec: Spec, results: str | Path, *, jobs: int = 1,
                   on_run: Callable[[Run, str], None] | None = None, launcher: str = "local",
                   cluster: Cluster | None = None, only: list[str] | tuple = (),
                   should_stop: Callable[[], bool] | None = None) -> list[Run]:
    """Plan, claim the results folder, and train every run not done (of those `only`'s patterns pick,
    `select`), `jobs` at a time, through the `launcher` (`LAUNCHERS`; `cluster` overrides the spec's
    resources). `on_run(run, event)` hears "done", "failed: <reason>" or "stopped at ..." as each run
    ends. Local launcher: once `should_stop()` (checked every POLL_S) says so, the runs in progress
    finish their update and write a checkpoint (status "stopped") and the runs not yet started stay as
    they were; an exception meanwhile (a second Ctrl-C) ends the workers at once. Returns the runs
    picked."""
    if jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {jobs}")
    check_launcher(launcher)
    runs = select(plan(spec, results), only)
    claim_results(spec, results)
    todo = [r for r in runs if r.status != "done"]
    if not todo:
        return runs
    if launcher != "local":
        _submitit(spec, Path(results), todo, jobs, launcher, cluster or spec.cluster, on_run)
        return runs
    import multiprocessing as mp

    context = mp.get_context("spawn")
    stop = context.Event()
    with ProcessPoolExecutor(max_workers=jobs, mp_context=context, initializer=_init_worker,
                             initargs=(stop,)) as pool:
        futures = {pool.submit(_train_one, run.config): run for run in todo}
        pending = set(futures)
        try:
            while pending:
                finished, pending = wait(pending, timeout=POLL_S, return_when=FIRST_COMPLETED)
                for future in finished:
                    if future.cancelled():
                        continue
                    event = _outcome(futures[future], future)
                    if on_run is not None:
                        on_run(futures[future], event)
                if should_stop is not None and not stop.is_set() and should_stop():
                    stop.set()
                    for future in pending:
                        future.cancel()  # not started: left as it was; started ones stop after their update
        except BaseException:
            stop.set()
            for child in mp.active_children():  # the pool's workers: their runs keep the last checkpoint
                child.terminate()
            raise
    return runs
