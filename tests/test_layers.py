"""The import layering holds (import-linter's contracts in pyproject.toml) and no module imports
itself through others (no import cycle anywhere in the library)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_layers_and_the_forbidden_imports_hold():
    lint = Path(sys.executable).with_name("lint-imports")
    result = subprocess.run([str(lint), "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True,
                            text=True)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "2 kept, 0 broken" in result.stdout


def test_no_import_cycles():
    import grimp

    graph = grimp.build_graph("illm_tools", include_external_packages=False)
    edges = {m: graph.find_modules_directly_imported_by(m) for m in graph.modules}
    index, low, stack, on, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for module in sorted(edges):
        if module not in index:
            visit(module)
    assert cycles == [], cycles


def test_the_target_provider_seam_is_an_import_the_contract_sees():
    """A bonus declares the kind of targets it reads (intrinsic/); rl/providers.py imports the kinds and
    the providers and maps one to the other: an arrow down, checked by lint-imports, where a bonus
    once named its provider as a "module:Class" string up the layers, which no contract can see."""
    import grimp

    graph = grimp.build_graph("illm_tools", include_external_packages=False)
    seam = graph.find_modules_directly_imported_by("illm_tools.rl.providers")
    assert {"illm_tools.intrinsic.base", "illm_tools.intrinsic.ellm", "illm_tools.rl.targets"} <= seam
    named = [p.name for p in (ROOT / "illm_tools" / "intrinsic").glob("*.py") if "illm_tools.rl.targets:" in p.read_text()]
    assert named == []
