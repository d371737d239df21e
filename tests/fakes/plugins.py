"""What a package outside illm would add: `plugins_installed` (entry points as an installed package
would declare them), a backend and a suite defined here (`TinyBackend`; `TinySuite` of the corridor
`TINY`, docs/examples' `Corridor`) and `EXAMPLES`, the plug-in examples the docs tell a user to
copy. Used by test_plugins.py, test_backends.py, test_suites.py, test_docs_examples.py,
test_example_level.py, test_example_bonus.py and test_oracles.py."""

from __future__ import annotations

import importlib.metadata
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from illm_tools.envs.suite import ObsSpec, Suite
from illm_tools.llm.stub import StubBackend


@contextmanager
def plugins_installed(monkeypatch, points: dict[str, list[tuple[str, str]]], also: tuple = ()) -> Iterator[list[list[str]]]:
    """Plug-ins as if installed: `importlib.metadata.entry_points` answers `points` ({group: [(name,
    "module:object")]}) for their groups and the installed ones for other groups; every registry
    reads them, and the registries in `also` (e.g. the oracles'). Yields the names each registry added
    (methods, tasks, backends, suites, then `also`'s in order); removes them after."""
    from illm_tools.envs import SUITES
    from illm_tools.intrinsic.registry import METHODS
    from illm_tools.llm.backend import BACKENDS
    from illm_tools.tasks.registry import LANGUAGE_TASKS

    real = importlib.metadata.entry_points

    def entry_points(**selection):
        group = selection.get("group")
        if group not in points:  # other libraries' look-ups: the installed ones
            return real(**selection)
        return [importlib.metadata.EntryPoint(name, value, group) for name, value in points[group]]

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    registries = (METHODS, LANGUAGE_TASKS, BACKENDS, SUITES, *also)
    added = [registry.read_plugins(again=True) for registry in registries]
    try:
        yield added
    finally:
        for registry, names in zip(registries, added):
            for name in names:
                del registry[name]


class TinyBackend(StubBackend):
    """A third backend, defined here: the stub under another name, with its own fingerprint."""

    name = "tiny"

    @classmethod
    def model_fingerprint(cls, model, *, dtype="bfloat16", quant="none"):
        return {"model_id": f"{cls.name}:{model}", "source": cls.name, "sha256": None, "revision": "1",
                "dtype": dtype, "quant": quant}


TINY = "Tiny-Corridor-v0"
EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"
"""The plug-in examples the docs tell a user to copy (test_docs_examples.py, test_example_*.py)."""


def _docs_example(name: str):
    """A module of docs/examples loaded from its file (under a name of its own, so the plug-in test that
    installs it as `corridor_suite` still imports it afresh): the docs' corridor is the tests' corridor."""
    import importlib.util

    path = EXAMPLES / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"illm_docs_example_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


Corridor = _docs_example("corridor_suite").Corridor
"""Cells in a row; 'go right' from the last but one reaches the goal (reward 1), the agent a key (MiniGrid
code 5) in a 7x7x3 grid: docs/examples/corridor_suite.py's environment."""


class TinySuite(Suite):
    name = "tiny"
    renderer = "tiny-text@1"
    description = "a corridor"

    def env_ids(self):
        return [TINY]

    def options(self, env_id):
        return ("length",)

    def make(self, env_id, *, action_space, render_text=True, **options):
        return Corridor(render_text=render_text, **options)

    def obs_spec(self, env_id):
        return ObsSpec(shape=(7, 7, 3), dtype="uint8", kind="grid", description="a corridor as MiniGrid codes")


