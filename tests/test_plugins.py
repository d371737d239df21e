"""Plug-ins from installed packages: a method, a language task, an LLM backend and two suites (one
with a kind of observation illm has never seen, its adapter and its torso), each defined in this file
and found only through a (fake) Python entry point of its group, run end to end (collect, annotate,
train with every bonus that reads observations) without editing the trainer, networks, bonuses or
any registry; and the one `Registry` shape: lazy entries, a type check, one unknown-name message."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from typing import Protocol

import pytest
import torch
from typer.testing import CliRunner

from cli.main import app
import numpy as np
from torch import nn

from illm_tools.cache import AnnotationCache
from illm_tools.envs.observations import Observation
from illm_tools.envs.suite import ObsSpec
from illm_tools.errors import UsageError
from illm_tools.intrinsic import BonusRewards, IntrinsicBonus, TargetProvider, Targets
from illm_tools.intrinsic.registry import METHODS, Method
from illm_tools.rl.networks import GridMissionNet
from illm_tools.rl.providers import TARGET_PROVIDERS, kind_name, provider_class
from illm_tools.rl.targets import CachedTargets
from illm_tools.registry import Registry
from illm_tools.tasks.registry import LanguageTask
from illm_tools.tasks.annotation_setup import adopt_model
from fakes import TINY, TinyBackend, TinySuite, cli_ok as ok, plugins_installed

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


class MarkedKind(TargetProvider, Protocol):
    """The kind of targets the told bonus reads: the cache's rows, through a provider of its own."""


class MarkedTargets(CachedTargets):
    """A plug-in method's own target provider (of `MarkedKind`, registered through the plug-in's
    `illm.target_providers` entry point): the cache's rows, counting the rollouts it answered."""

    calls = 0

    def targets(self, records):
        MarkedTargets.calls += 1
        return super().targets(records)


class ToldBonus(IntrinsicBonus):
    """Pays 1 where its own provider found the state's action row: a method that brings its provider."""

    needs_targets = True
    target_tasks = ("action",)
    target_kind = MarkedKind
    told = MarkedTargets
    """The provider class the run must hand it: the one registered for its kind."""

    def __init__(self, config, ctx):
        self.provider = None

    def use_provider(self, provider):
        self.provider = provider

    def compute_rewards(self, batch):
        assert isinstance(self.provider, self.told)  # the run's provider is the one registered for its kind
        return BonusRewards(batch["target_mask"].float(), {"told_calls": float(self.told.calls)})


class EchoBackend(TinyBackend):
    """test_backends' tiny backend under another name, with its own fingerprint."""

    name = "echo"
    default_model = "echo:8"


class RulerObservation(Observation):
    """A new kind: the corridor as a float vector, one-hot of the agent's cell (no grid, no picture)."""

    kind = "ruler"

    def encoder(self, hidden, out):
        return nn.Sequential(nn.Linear(self.shape[0], hidden), nn.Tanh(), nn.Linear(hidden, out))


class RulerNet(GridMissionNet):
    """The plug-in's torso for its kind: an MLP on the vector (the mission is fixed, not read)."""

    kinds = ("ruler",)

    def build_torso(self, *, vocab_size, image_shape, options=None, **_):
        self.mlp = nn.Sequential(nn.Linear(self.observation.shape[0], 32), nn.Tanh())
        return 32

    def features(self, images, missions):
        return self.mlp(images.float())


class RulerSuite(TinySuite):
    """The tiny corridor, seen as a `ruler` vector through the suite's own adapter and network."""

    name = "ruler"
    network = f"{__name__}:RulerNet"

    def env_ids(self):
        return [RULER]

    def obs_spec(self, env_id):
        return ObsSpec(shape=(7,), dtype="float32", kind="ruler", description="the agent's cell, one-hot")

    def observation(self, env_id):
        return RulerObservation(self.obs_spec(env_id))

    def policy_obs(self, obs):
        return (obs[:, 3, 0] == 5).astype(np.float32)


RULER = "Ruler-Corridor-v0"
PLUGIN_METHOD = Method("flat", "a flat bonus from a plug-in package", FlatBonus)
TOLD_METHOD = Method("told", "paid where its own target provider answers", ToldBonus)
PLUGIN_SUITE = TinySuite()
PLUGIN_RULER = RulerSuite()
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
        "illm.methods": [("flat", f"{__name__}:PLUGIN_METHOD"), ("told", f"{__name__}:TOLD_METHOD")],
        "illm.tasks": [("verdict", f"{__name__}:PLUGIN_TASK")],
        "illm.backends": [("echo", f"{__name__}:EchoBackend")],
        "illm.suites": [("tiny", f"{__name__}:PLUGIN_SUITE"), ("ruler", f"{__name__}:PLUGIN_RULER")],
        "illm.target_providers": [(kind_name(MarkedKind), f"{__name__}:MarkedTargets")],
    }

    with plugins_installed(monkeypatch, points, also=(TARGET_PROVIDERS,)) as added:
        yield added[:4]


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_a_plugin_of_each_kind_loads_through_its_entry_point_and_runs(plugins, tmp_path):
    assert plugins == [["flat", "told"], ["verdict"], ["echo"], ["tiny", "ruler"]]
    ok("collect", "--env", TINY, "--steps", 48, "--num-envs", 2, "--out", tmp_path / "traj")
    ok("annotate", tmp_path / "traj", "--cache", tmp_path / "ann", "--backend", "echo", "--history", 0,
       "--tasks", "action,verdict")
    cache = AnnotationCache(tmp_path / "ann")
    assert set(cache.tasks()) == {"action", "verdict"}  # the plug-in task annotated beside the action task
    found = adopt_model(cache)  # the rows' fingerprint reproduced by the plug-in backend
    assert (found["backend"], found["model"]) == ("echo", "echo:8")
    ok("train", "--env", TINY, "--method", "illm", "--backend", "echo", "--cache", tmp_path / "ann", "--history", 0,
       "--tasks", "action,verdict", "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", "all",
       "--live-mode", "sync", "--out", tmp_path / "illm")
    ok("train", "--env", TINY, "--method", "flat", "--bonus-option", "pay=0.5", "--num-envs", 2, "--num-steps", 16,
       "--frames", 32, "--out", tmp_path / "flat")
    with open(tmp_path / "flat" / "metrics.csv", newline="") as fh:
        assert float(next(csv.DictReader(fh))["adv_int_abs"]) > 0  # the plug-in's bonus reached the advantages
    with open(tmp_path / "illm" / "metrics.csv", newline="") as fh:
        assert all(float(r["target_coverage"]) == 1.0 for r in csv.DictReader(fh))
    # a method that reads a kind of targets of its own: the run reads the cache through the provider its
    # package registered for that kind, no trainer edit
    ok("train", "--env", TINY, "--method", "told", "--backend", "echo", "--cache", tmp_path / "ann", "--history", 0,
       "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--out", tmp_path / "told")
    with open(tmp_path / "told" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert MarkedTargets.calls == len(rows)  # once per rollout; the bonus checked it is its provider
    assert float(rows[-1]["target_coverage"]) == 1.0 and float(rows[-1]["adv_int_abs"]) > 0


@pytest.mark.parametrize("method", ["ppo", "rnd", "ngu", "apt", "flat"])
def test_a_suite_with_a_new_kind_of_observation_trains_with_every_bonus(plugins, method, tmp_path):
    """The suite brings its adapter and torso; the bonuses read the vector through the adapter."""
    ok("train", "--env", RULER, "--method", method, "--num-envs", 2, "--num-steps", 16, "--frames", 64,
       "--out", tmp_path / "run")
    with open(tmp_path / "run" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and all(np.isfinite(float(r["policy_loss"])) for r in rows)
    if method != "ppo":
        assert float(rows[-1]["adv_int_abs"]) > 0  # the bonus read the new kind and reached the advantages
    (result,) = json.loads(ok("eval", tmp_path / "run", "--episodes", 4, "--json"))
    assert result["env_id"] == RULER and result["episodes"] == 4


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


class TinyKind(TargetProvider, Protocol):
    """A kind of targets of a plug-in's own: every state's, with no LLM asked."""


class TinyTargets:
    """The tiny provider of `TinyKind`: every state has a target, the uniform distribution over the actions."""

    built: list[TinyTargets] = []
    calls = 0

    def __init__(self, num_actions: int):
        self.num_actions = num_actions
        TinyTargets.built.append(self)

    @classmethod
    def for_run(cls, cfg, cache, builder, *, num_actions, live=None, shuffle_seed=None):
        return cls(num_actions)

    def targets(self, records):
        TinyTargets.calls += 1
        b = len(records)
        return Targets(np.full((b, self.num_actions), 1.0 / self.num_actions, np.float32), np.zeros((b, 0), np.float32),
                       np.ones(b, bool))

    def stats(self):
        return {"cache_hit_rate": 1.0, "target_coverage": 1.0, "live_annotations": 0.0}

    def close(self):
        pass


class TinyToldBonus(ToldBonus):
    """The told bonus reading `TinyKind`: the run must hand it the tiny provider."""

    target_kind = TinyKind
    told = TinyTargets


def test_a_bonus_declares_its_kind_of_targets_and_the_run_hands_it_the_provider_registered_for_it(tmp_path):
    with pytest.raises(UsageError, match="no target provider serves .*TinyKind"):
        provider_class(TinyToldBonus)  # nothing registered for the kind yet: one line naming it
    METHODS.register("tiny-told", Method("tiny-told", "paid where the tiny provider answers", TinyToldBonus))
    TARGET_PROVIDERS.register(kind_name(TinyKind), TinyTargets)
    TinyTargets.built.clear()
    TinyTargets.calls = 0
    try:
        assert provider_class(TinyToldBonus) is TinyTargets
        ok("train", "--env", "BabyAI-GoToLocal-v0", "--method", "tiny-told", "--backend", "stub", "--cache",
           tmp_path / "ann", "--live-budget", 1, "--live-mode", "sync", "--num-envs", 2, "--num-steps", 16,
           "--frames", 64, "--out", tmp_path / "run")
    finally:
        del METHODS["tiny-told"]
        del TARGET_PROVIDERS[kind_name(TinyKind)]
    with open(tmp_path / "run" / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(TinyTargets.built) == 1 and TinyTargets.calls == len(rows) == 2  # built once, asked once per rollout
    assert float(rows[-1]["target_coverage"]) == 1.0 and float(rows[-1]["adv_int_abs"]) > 0


class FirstActionPolicy:
    """A collection policy the collect stage has never heard of: always the first action."""

    name = "first"

    def __init__(self, pool):
        self.num_envs = pool.num_envs

    def act(self, obs):
        return np.zeros(self.num_envs, dtype=np.int64)


def test_a_collection_policy_is_one_factory_and_one_registry_entry(tmp_path):
    from illm_tools.collect import POLICIES
    from illm_tools.data.trajectories import open_table

    POLICIES.register("first", lambda config, pool: FirstActionPolicy(pool))
    try:
        ok("collect", "--env", "BabyAI-GoToLocal-v0", "--policy", "first", "--steps", 32, "--num-envs", 2,
           "--out", tmp_path / "traj")
        actions = open_table(tmp_path / "traj", columns=["action"])["action"].to_pylist()
        assert len(actions) == 32 and set(actions) == {0}
    finally:
        del POLICIES["first"]
    refused = runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocal-v0", "--policy", "first", "--steps", "8",
                                  "--out", str(tmp_path / "again")])
    assert refused.exit_code != 0 and "Traceback" not in refused.output  # no longer a policy: read as a run folder
