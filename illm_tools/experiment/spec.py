"""An `illm experiment`'s spec file (its format: the package's docstring) read and checked for
shape: `Spec`, `load_spec`, and `Cluster`, its `cluster:` block (a run's job resources under a
scheduler). Its names and values are checked when its grid is planned (`plan.py`), except the names
that become folders, checked here: the spec's `name` (the default results folder) and each bundle's
`name` (part of its runs' folders) are bare names (`illm_tools.folders.bare_name`), never `../x`."""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from illm_tools.errors import UsageError
from illm_tools.folders import bare_name

TOP_KEYS = ("name", "frames", "env_frames", "seeds", "envs", "methods", "grid", "method_grid", "settings",
            "method_settings", "description", "paper", "cluster")
REQUIRED = ("envs", "methods")


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


@dataclass
class Spec:
    """An experiment spec as read and checked for shape (`load_spec`), before `plan` checks its names."""

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
                if isinstance(value, dict):  # its name is part of its runs' folders
                    bare_name(str(value["name"]), f"{path} line {spec_lines.get((*where, key), '?')}: the bundle name",
                              "name it without / or ..")
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
    name = bare_name(str(data.get("name") or path.stem), f"{path} line {spec_lines.get(('name',), '?')}: name",
                     "the spec's name is its results folder's (results/NAME): name it without / or ..")
    return Spec(name=name, path=path, text=text, frames=total, seeds=seed_list,
                env_frames={str(k): int(v) for k, v in env_frames.items()},
                envs=envs, methods=[str(m) for m in as_list("methods")], grid=grid,
                method_grid=method_grid, settings=settings, method_settings=per_method, paper=paper or {},
                cluster=cluster, lines=spec_lines)
