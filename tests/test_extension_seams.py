"""The extension seams name nothing up the layers, and a plug-in cannot take a built-in's name: a suite
says which policy network reads it by a plain name the rl layer resolves (`NETWORKS`), the rl layer
registers its own method (chibit) without making `--help` import torch, no library string names a
higher layer's "module:attribute", and an installed `illm.methods` entry point named as a built-in is
refused in one line naming both."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.envs import SUITES
from illm_tools.errors import UsageError
from illm_tools.intrinsic.registry import METHODS, get_method, method_help
from illm_tools.rl.networks import NETWORKS, FrameNet, GlyphNet, GridMissionNet, network_class

ROOT = Path(__file__).resolve().parent.parent
runner = CliRunner()


# --- networks by name ---------------------------------------------------------------------------
@pytest.mark.parametrize("suite, name, cls", [("babyai", "grid-mission", GridMissionNet),
                                              ("minihack", "glyph", GlyphNet), ("crafter", "frame", FrameNet),
                                              ("atari", "frame", FrameNet)])
def test_a_suite_names_its_network_and_the_rl_layer_resolves_it(suite, name, cls):
    assert SUITES[suite].network == name and name in NETWORKS
    assert network_class(SUITES[suite].network, f"suite {suite}: network") is cls


def test_module_class_references_still_resolve_and_an_unknown_name_is_refused_in_one_line():
    # the form every suite used before the names (and a plug-in suite's own class, tests/test_plugins.py)
    assert network_class("illm_tools.rl.networks:GlyphNet", "suite s: network") is GlyphNet
    assert network_class(FrameNet, "suite s: network") is FrameNet
    with pytest.raises(UsageError) as err:
        network_class("grid", "suite corridor: network")
    said = str(err.value)
    assert "\n" not in said and "suite corridor: network: unknown network 'grid'" in said and "grid-mission" in said
    with pytest.raises(TypeError, match="is not a GridMissionNet subclass"):
        network_class("illm_tools.errors:UsageError", "suite s: network")


def test_no_library_string_names_a_module_of_a_higher_layer():
    """Every "illm_tools.X:attr" string constant of the library names its own layer or one below it
    (pyproject.toml's layers): an import up the layers hidden in a string is one no contract sees."""
    contract = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]
    rank = {module.strip(): i for i, layer in enumerate(contract["layers"])
            for module in re.split(r"[:|]", layer) if module.strip()}

    def layer_of(module: str) -> int | None:
        parts = module.split(".")
        return next((rank[".".join(parts[:n])] for n in range(len(parts), 0, -1) if ".".join(parts[:n]) in rank),
                    None)

    reference, up = re.compile(r"^(illm_tools(?:\.\w+)+):[\w.]+$"), []
    for path in sorted((ROOT / "illm_tools").rglob("*.py")):
        own = layer_of(".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"))
        for node in ast.walk(ast.parse(path.read_text())):
            named = isinstance(node, ast.Constant) and isinstance(node.value, str) and reference.match(node.value)
            if named and own is not None and (layer_of(named.group(1)) or own) < own:
                up.append(f"{path.relative_to(ROOT)}: {node.value}")
    assert up == []


# --- chibit, registered by the rl layer -----------------------------------------------------------
def test_chibit_comes_from_the_rl_layer_and_help_lists_it_without_torch():
    method = get_method("chibit")
    assert method.entry_point is None and not method.pays and method.network_class.__name__ == "ChibiTNet"
    assert method.network_class.__module__ == "illm_tools.rl.chibit"
    code = ("import sys; from illm_tools.intrinsic.registry import METHODS, method_help; "
            "assert 'chibit' not in list(METHODS), 'registered below the rl layer'; "
            "import illm_tools.rl.config; assert 'chibit (' in method_help(); "
            "assert 'torch' not in sys.modules, 'torch imported'")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    out = runner.invoke(app, ["train", "--help"])
    assert out.exit_code == 0 and "chibit" in out.output


# --- a plug-in with a built-in's name ---------------------------------------------------------------
TINY = '''
from illm_tools.intrinsic.registry import Method

METHOD = Method("rnd", "a tiny plug-in that wants rnd's name", None, pays_reward=False)
OTHER = Method("tiny-other", "the same package's other method", None, pays_reward=False)
'''


@pytest.fixture
def clashing_plugin(tmp_path, monkeypatch):
    """A tiny installed package whose `illm.methods` entry points are `rnd` (a built-in's name) and
    `tiny-other`; the registry reads the installed ones again afterwards."""
    (tmp_path / "tiny_clash.py").write_text(TINY)
    monkeypatch.syspath_prepend(str(tmp_path))
    real = importlib.metadata.entry_points
    points = [importlib.metadata.EntryPoint("rnd", "tiny_clash:METHOD", "illm.methods"),
              importlib.metadata.EntryPoint("tiny-other", "tiny_clash:OTHER", "illm.methods")]

    def entry_points(**selection):
        return points if selection.get("group") == "illm.methods" else real(**selection)

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    try:
        yield
    finally:
        monkeypatch.setattr(importlib.metadata, "entry_points", real)
        if "tiny-other" in METHODS:
            del METHODS["tiny-other"]
        METHODS.read_plugins(again=True)


def test_a_plugin_method_named_as_a_built_in_is_refused_in_one_line(clashing_plugin, tmp_path):
    assert METHODS.read_plugins(again=True) == ["tiny-other"]
    with pytest.raises(UsageError) as err:
        get_method("rnd")
    said = str(err.value)
    assert "\n" not in said and "plug-in method 'rnd' (tiny_clash:METHOD, entry point group illm.methods)" in said
    assert "built-in method 'rnd' (Random Network Distillation" in said and "another name" in said
    out = runner.invoke(app, ["train", "--method", "rnd", "--frames", "64", "--out", str(tmp_path / "run")])
    assert out.exit_code == 1 and "plug-in method 'rnd'" in out.output and len(out.output.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()
    # the rest works on: the built-in's entry is kept for --help, the package's other method is in
    assert get_method("tiny-other").summary == "the same package's other method" and get_method("ppo").name == "ppo"
    assert "rnd (Random Network Distillation" in method_help() and "tiny-other" in method_help()


def test_a_built_in_registered_after_the_plugins_were_read_is_refused_the_same_way(clashing_plugin):
    from illm_tools.intrinsic.registry import Method, register

    points = [importlib.metadata.EntryPoint("late", "tiny_clash:OTHER", "illm.methods")]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(importlib.metadata, "entry_points",
                      lambda **selection: points if selection.get("group") == "illm.methods" else [])
        assert METHODS.read_plugins(again=True) == ["late"]
    try:
        register(Method("late", "a method of the layer above, registered on its import", None, pays_reward=False))
        with pytest.raises(UsageError, match=r"plug-in method 'late' \(tiny_clash:OTHER.*built-in method 'late' "
                                             r"\(a method of the layer above"):
            get_method("late")
    finally:
        METHODS.pop("late")
