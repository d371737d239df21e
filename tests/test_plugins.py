"""Plug-ins from installed packages: a method, a language task, an LLM backend and a suite, each
defined in this file and found only through a (fake) Python entry point of its group, run end to end
(collect, annotate, train) without editing the trainer, networks, bonuses or any registry; and the
one `Registry` shape: lazy entries, a type check, one unknown-name message."""

from __future__ import annotations

import csv
import importlib.metadata
from dataclasses import dataclass

import pytest
import torch
from typer.testing import CliRunner

from cli.main import app
from illm_tools.envs import SUITES
from illm_tools.errors import UsageError
from illm_tools.intrinsic import BonusRewards, IntrinsicBonus
from illm_tools.intrinsic.registry import METHODS, Method
from illm_tools.llm.backend import BACKENDS
from illm_tools.llm.stub import StubBackend
from illm_tools.registry import Registry
from illm_tools.tasks.registry import LANGUAGE_TASKS, LanguageTask
from test_suites import TINY, TinySuite

runner = CliRunner()


@dataclass
class FlatConfig:
    """The plug-in bonus's settings."""

    pay: float = 0.25
    """The reward of every step."""


class FlatBonus(IntrinsicBonus):
    """Pays a flat reward: the smallest bonus that still reaches the advantages."""

    config_class = FlatConfig

    def __init__(self, config: FlatConfig, ctx):
        self.pay = config.pay

    def compute_rewards(self, batch):
        return BonusRewards(torch.full(batch["actions"].shape, self.pay), {"flat_paid": self.pay})


class EchoBackend(StubBackend):
    """The stub under another name, with its own fingerprint."""

    name = "echo"
    default_model = "echo:8"

    @staticmethod
    def model_fingerprint(model, *, dtype="bfloat16", quant="none"):
        return {"model_id": f"echo:{model}", "source": "echo", "sha256": None, "revision": "1", "dtype": dtype,
                "quant": quant}


PLUGIN_METHOD = Method("flat", "a flat bonus from a plug-in package", FlatBonus)
PLUGIN_SUITE = TinySuite()
PLUGIN_TASK: LanguageTask | None = None  # made by the fixture: its template lives in a temporary folder


@pytest.fixture
def plugins(tmp_path, monkeypatch):
    """Entry points of all four groups, as an installed package would declare them."""
    global PLUGIN_TASK
    (tmp_path / "templates").mkdir()
    (tmp_path / "templates" / "verdict.txt").write_text(
        "You are an expert player playing {task}\nRecent player's history: {history}\nIs this going well?\nVerdict:\n")
    PLUGIN_TASK = LanguageTask("verdict", "text", {"shared": ("verdict", 1), "paper": ("verdict", 1)},
                               max_new_tokens=8, template_dir=str(tmp_path / "templates"))
    points = {
        "illm.methods": [("flat", f"{__name__}:PLUGIN_METHOD")],
        "illm.tasks": [("verdict", f"{__name__}:PLUGIN_TASK")],
        "illm.backends": [("echo", f"{__name__}:EchoBackend")],
        "illm.suites": [("tiny", f"{__name__}:PLUGIN_SUITE")],
    }

    real = importlib.metadata.entry_points

    def entry_points(**selection):
        if selection.get("group") not in points:  # other libraries' look-ups: the installed ones
            return real(**selection)
        group = selection["group"]
        return [importlib.metadata.EntryPoint(name, value, group) for name, value in points[group]]

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    registries = (METHODS, LANGUAGE_TASKS, BACKENDS, SUITES)
    added = [registry.read_plugins(again=True) for registry in registries]
    yield added
    for registry, names in zip(registries, added):
        for name in names:
            del registry[name]


def ok(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


def test_a_plugin_of_each_kind_loads_through_its_entry_point_and_runs(plugins, tmp_path):
    assert plugins == [["flat"], ["verdict"], ["echo"], ["tiny"]]
    ok("collect", "--env", TINY, "--steps", 48, "--num-envs", 2, "--out", tmp_path / "traj")
    said = ok("annotate", tmp_path / "traj", "--cache", tmp_path / "ann", "--backend", "echo", "--history", 0,
              "--tasks", "action,verdict")
    assert "(" in said and "verdict" in said
    assert "--backend echo --model echo:8" in ok("cache", "info", tmp_path / "ann")
    ok("train", "--env", TINY, "--method", "illm", "--backend", "echo", "--cache", tmp_path / "ann", "--history", 0,
       "--tasks", "action,verdict", "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", "all",
       "--live-mode", "sync", "--out", tmp_path / "illm")
    ok("train", "--env", TINY, "--method", "flat", "--bonus-option", "pay=0.5", "--num-envs", 2, "--num-steps", 16,
       "--frames", 32, "--out", tmp_path / "flat")
    with open(tmp_path / "flat" / "metrics.csv", newline="") as fh:
        assert float(next(csv.DictReader(fh))["adv_int_abs"]) > 0  # the plug-in's bonus reached the advantages
    with open(tmp_path / "illm" / "metrics.csv", newline="") as fh:
        assert all(float(r["target_coverage"]) == 1.0 for r in csv.DictReader(fh))


def test_one_registry_shape_lazy_checked_and_one_message():
    reg: Registry = Registry("widget", "illm.widgets", check=int, hint="--widget")
    reg.register("one", 1)
    reg.register("lazy", "math:pi")  # not imported until used
    assert reg.entry("lazy") == "math:pi" and list(reg) == ["one", "lazy"]
    with pytest.raises(TypeError, match="widget 'lazy' .* is not a int instance"):
        reg.load("lazy")
    with pytest.raises(UsageError, match="unknown widget 'two'; choose one of one, lazy"):
        reg.load("two")
    with pytest.raises(UsageError, match="a widget named 'one' is already registered"):
        reg.register("one", 2)
    reg["one"] = 2  # code may replace an entry on purpose
    assert reg["one"] == 2
