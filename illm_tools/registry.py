"""One registry shape for every kind of plug-in: training methods, language tasks, LLM backends,
environment suites and oracles (`illm_tools.intrinsic.registry.METHODS`,
`illm_tools.tasks.registry.LANGUAGE_TASKS`, `illm_tools.llm.backend.BACKENDS`, `illm_tools.envs.SUITES`,
`illm_tools.oracles.registry.ORACLES`).

A `Registry` maps a name to an entry: the object itself, or "module:attribute", imported the first
time the entry is used (so `illm --help` imports no simulator, torch or model code). A loaded entry
is checked by the registry's `check` (a base class, or a function saying what is wrong), once. An
unknown name is refused in one line that lists the known ones. Entries come from three places, in
this order: the built-ins (registered by the module that owns the registry), code (`register`, or
`registry[name] = entry`), and installed packages through Python entry points of the registry's
group (`illm.methods`, `illm.tasks`, `illm.backends`, `illm.suites`, `illm.observations`, `illm.oracles`), read
once, on the first look-up:

    # a plug-in package's pyproject.toml
    [project.entry-points."illm.methods"]
    mybonus = "mypackage.bonus:METHOD"

Hand-written rather than taken from a library: pluggy and stevedore bring hook specs and driver
managers this needs none of; what is needed is a dict with lazy loading, a type check and one error
message, shared by four registries that each had their own copy.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, MutableMapping
from typing import Any, Generic, TypeVar

from illm_tools.errors import UsageError

T = TypeVar("T")

ENTRY_POINT_GROUPS = ("illm.methods", "illm.tasks", "illm.backends", "illm.suites", "illm.observations", "illm.oracles")


def load_reference(ref: str) -> Any:
    """The attribute "module:attribute" names, imported now."""
    module, sep, attr = ref.partition(":")
    if not sep or not module or not attr:
        raise ValueError(f"{ref!r} is not a 'module:attribute' reference")
    target: Any = importlib.import_module(module)
    for part in attr.split("."):
        target = getattr(target, part)
    return target


def load_class(ref: str | type, base: type, what: str) -> type:
    """The class `ref` names ("module:Class", imported now) or is, checked to subclass `base`."""
    cls = load_reference(ref) if isinstance(ref, str) else ref
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise TypeError(f"{what} {ref!r} is not a {base.__name__} subclass")
    return cls


class Registry(MutableMapping, Generic[T]):
    """Named plug-ins of one kind (see the module docstring)."""

    def __init__(self, kind: str, group: str, *, check: type | Callable[[Any], str | None] | None = None,
                 instance: bool = True, hint: str = ""):
        """kind: what an entry is, for messages ("method", "LLM backend"); group: the entry-point
        group; check: a base class (entries are its instances, or with `instance=False` its
        subclasses) or a function returning what is wrong with an entry (None: fine); hint: the
        option that names an entry ("--method"), for the unknown-name message."""
        self.kind, self.group, self.check, self.instance, self.hint = kind, group, check, instance, hint
        self._entries: dict[str, Any] = {}
        self._loaded: dict[str, T] = {}
        self._plugins_read = False

    # --- registering ----------------------------------------------------------------------------
    def register(self, name: str, entry: Any, *, replace: bool = False) -> Any:
        """Add `entry` (an object, or "module:attribute") as `name`; a taken name is refused unless `replace`."""
        if name in self._entries and not replace:
            raise UsageError(f"a {self.kind} named {name!r} is already registered")
        self._entries[name] = entry
        self._loaded.pop(name, None)
        return entry

    def read_plugins(self, *, again: bool = False) -> list[str]:
        """Register the entry points of the registry's group (installed packages' plug-ins) not
        registered yet; returns their names. Read once unless `again`."""
        if self._plugins_read and not again:
            return []
        self._plugins_read = True
        from importlib.metadata import entry_points

        added = []
        for point in entry_points(group=self.group):
            if point.name not in self._entries:
                self._entries[point.name] = point.value
                added.append(point.name)
        return added

    # --- looking up -------------------------------------------------------------------------------
    def get(self, name: str, default: Any = None) -> T | Any:  # type: ignore[override]
        return self[name] if name in self else default

    def load(self, name: str) -> T:
        """The entry called `name`, imported and checked; one line listing the known ones otherwise."""
        if name not in self:
            raise UsageError(self.unknown(name))
        if name not in self._loaded:
            entry = self._entries[name]
            obj = load_reference(entry) if isinstance(entry, str) else entry
            problem = self._problem(obj)
            if problem:
                raise TypeError(f"{self.kind} {name!r} ({entry!r}): {problem}")
            self._loaded[name] = obj
        return self._loaded[name]

    def unknown(self, name: Any) -> str:
        """The message for a name nobody registered."""
        return f"unknown {self.kind} {name!r}; choose one of {', '.join(self)}"

    def _problem(self, obj: Any) -> str | None:
        if self.check is None:
            return None
        if isinstance(self.check, type):
            ok = isinstance(obj, self.check) if self.instance else isinstance(obj, type) and issubclass(obj, self.check)
            return None if ok else f"is not a {self.check.__name__} {'instance' if self.instance else 'subclass'}"
        return self.check(obj)

    # --- the mapping ------------------------------------------------------------------------------
    def __getitem__(self, name: str) -> T:
        return self.load(name)

    def __setitem__(self, name: str, entry: Any) -> None:
        self.register(name, entry, replace=True)

    def __delitem__(self, name: str) -> None:
        del self._entries[name]
        self._loaded.pop(name, None)

    def __contains__(self, name: object) -> bool:
        if isinstance(name, str) and name not in self._entries:
            self.read_plugins()
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        self.read_plugins()
        return iter(list(self._entries))

    def __len__(self) -> int:
        self.read_plugins()
        return len(self._entries)

    def entry(self, name: str) -> Any:
        """What `name` was registered as (the reference string, or the object), without loading it."""
        if name not in self:
            raise UsageError(self.unknown(name))
        return self._entries[name]

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {list(self._entries)})"
