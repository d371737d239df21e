"""The whole job through the command line, one parametrized test over the suites and backends that
need it: collect, annotate (a tiny random transformers model, or the stub), `cache info` and
`cache verify`, train illm from the cache with the live fallback writing its answers back (and, in
hop mode, a cold run whose first states are the collection's: the trainer's keys are annotate's),
resume, the baselines, eval with the suite's score. BabyAI's case also collects with a trained
policy, compares runs with `eval` and `report`, and runs under every Python warning made an error
with no library logger speaking (nothing of a third party spills into illm's output); Atari's text-less
case refuses annotate and chibit in one line. Plus: a damaged shard named and refused, and train
without a cache saying what to do."""

from __future__ import annotations

import csv
import json
import logging
import warnings
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass

import pytest
from typer.testing import CliRunner

from cli.main import app
from fakes import cli_ok as ok

runner = CliRunner()
pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")
REQUIRED = {"global_step", "episodic_return", "success_rate", "sps", "intrinsic_reward_a", "intrinsic_reward_hc",
            "cache_hit_rate", "target_coverage", "live_annotations"}
OWN = ("illm_tools", "cli", "illm")
LIBRARIES = ("transformers", "datasets", "accelerate", "peft", "torch", "gymnasium", "huggingface_hub")
"""Their loggers, some of which (transformers, datasets) keep their own handler and do not propagate:
the strict cases listen to each directly."""


def metrics(run) -> list[dict]:
    with open(run / "metrics.csv", newline="") as fh:
        return list(csv.DictReader(fh))


@dataclass(frozen=True)
class Case:
    env: str
    backend: str | None
    """"tiny": the tiny random Llama (conftest's `tiny_lm`); "stub"; None: the suite has no text."""
    mode: str = "obs"
    history: int = 0
    options: tuple = ()
    steps: int = 64
    num_envs: int = 2
    num_steps: int = 16
    frames: int = 32
    limit: int = 6
    live: int = 2
    baselines: tuple = ("rnd",)
    resume: bool = False
    strict: bool = False
    """Every Python warning an error, no library logger at warning level, through every stage."""


CASES = {
    "babyai-tiny": Case("BabyAI-GoToLocal-v0", "tiny", history=3, num_envs=4, num_steps=32, frames=256, limit=10,
                        live=4, baselines=("ppo",), resume=True, strict=True),
    "minihack-tiny": Case("MiniHack-River-Monster-v0", "tiny", steps=96, num_steps=32, frames=128),
    "crafter-tiny": Case("CrafterReward-v1", "tiny", options=("length=40",), steps=96, num_steps=32, frames=128),
    "multiroom-stub": Case("MiniGrid-MultiRoom-N6-v0", "stub", live=0, baselines=("ppo",), strict=True),
    "multiroom-stub-hop": Case("MiniGrid-MultiRoom-N6-v0", "stub", mode="hop", live=0, baselines=()),
    "multiroom-tiny-hop": Case("MiniGrid-MultiRoom-N6-v0", "tiny", mode="hop", history=1, steps=48, limit=5,
                               baselines=(), resume=True),
    "atari-tiny-hop": Case("ALE/MontezumaRevenge-v5", "tiny", mode="hop", history=1, steps=48, limit=5,
                           options=("max_num_frames_per_episode=400",), baselines=(), resume=True),
    "atari-no-text": Case("ALE/MontezumaRevenge-v5", None, options=("max_num_frames_per_episode=200",),
                          num_steps=32, frames=128, baselines=("ppo", "rnd")),
}
FAST = {"multiroom-stub", "multiroom-stub-hop"}


def params():
    """The cases by name: the stub's in the fast tier, the strict ones with every warning an error from the
    start (fixtures included)."""
    for name, case in CASES.items():
        marks = ([] if name in FAST else [pytest.mark.slow]) + ([pytest.mark.filterwarnings("error")] if case.strict
                                                               else [])
        yield pytest.param(name, marks=marks, id=name)


@contextmanager
def no_foreign_warnings(caplog):
    """Every warning an error; afterwards, no record at warning level from a logger not illm's."""
    loggers = [logging.getLogger(name) for name in LIBRARIES]
    for logger in loggers:
        logger.addHandler(caplog.handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with caplog.at_level(logging.WARNING):
                yield
    finally:
        for logger in loggers:
            logger.removeHandler(caplog.handler)
    foreign = [f"{r.name}: {r.getMessage()}" for r in caplog.records
               if r.levelno >= logging.WARNING and not r.name.startswith(OWN)]
    assert not foreign, foreign


@pytest.mark.parametrize("name", params())
def test_collect_annotate_train_eval(name, tmp_path, request, caplog):
    case = CASES[name]
    env = ["--env", case.env, *[x for o in case.options for x in ("--env-option", o)]]
    model = []
    if case.backend == "tiny":
        lm = request.getfixturevalue("tiny_lm")
        model = ["--model", lm.spec.path, "--dtype", "float32"]
    elif case.backend == "stub":
        model = ["--backend", "stub", "--model", "stub:24"]
    traj, ann, run = tmp_path / "traj", tmp_path / "ann", tmp_path / "illm"
    shape = ["--num-envs", case.num_envs, "--num-steps", case.num_steps, "--seed", 0]
    with no_foreign_warnings(caplog) if case.strict else nullcontext():
        ok("collect", *env, "--steps", case.steps, "--num-envs", case.num_envs, "--out", traj)
        collected = json.loads(ok("data", "info", traj, "--json"))
        assert collected["rows"] == case.steps
        if case.backend is None:
            return _no_text(case, env, shape, traj, collected, tmp_path)
        setup = [*model, "--mode", case.mode, "--history", case.history]
        said = ok("annotate", traj, "--cache", ann, *setup, "--limit", case.limit, "--batch-size", 4)
        assert f"annotated {case.limit} states ({2 * case.limit} rows" in said
        info = json.loads(ok("cache", "info", ann, "--json"))
        assert info["tasks"] == {"action": case.limit, "summary": case.limit}
        if case.backend == "tiny":
            assert info["embedding_dims"] == [lm.hidden_size]
        assert ok("cache", "verify", ann).strip().endswith("ok")

        illm = ["train", *env, "--method", "illm", "--cache", ann, *setup]
        train = [*illm, *shape]
        if case.mode == "hop":  # the collection's episodes start from the same seeds: their first states are cached
            ok(*illm, "--num-envs", 2, "--num-steps", 4, "--frames", 8, "--live-budget", 0, "--out", tmp_path / "cold")
            assert float(metrics(tmp_path / "cold")[0]["cache_hit_rate"]) > 0  # the trainer's keys are annotate's
        ok(*train, "--frames", case.frames, "--live-budget", case.live, "--live-mode", "sync", "--out", run)
        rows = metrics(run)
        updates = case.frames // (case.num_envs * case.num_steps)
        assert REQUIRED <= set(rows[0]) and len(rows) == updates
        live = [float(r["live_annotations"]) for r in rows]
        assert live == [case.live] * updates  # per rollout, each written back to the shared cache
        assert json.loads(ok("cache", "info", ann, "--json"))["tasks"]["action"] == case.limit + sum(live)
        if case.resume:
            step = case.frames // updates  # one update more
            ok(*train, "--frames", case.frames + step, "--live-budget", case.live, "--live-mode", "sync", "--out", run,
               "--resume")
            assert [int(r["global_step"]) for r in metrics(run)] == list(range(step, case.frames + step + 1, step))
        for method in case.baselines:
            ok("train", *env, "--method", method, *shape, "--frames", case.frames, "--out", tmp_path / method)
            assert len(metrics(tmp_path / method)) == updates
        (result,) = json.loads(ok("eval", run, "--episodes", 2, "--json"))
        assert result["env_id"] == case.env and result["episodes"] == 2 and result["score"] == result["score"]
        if name == "babyai-tiny":
            _babyai_extras(env, run, tmp_path)


def _babyai_extras(env, run, tmp_path) -> None:
    """A trained policy collects; eval and report compare runs of two methods."""
    ppo = tmp_path / "ppo"
    ok("collect", *env, "--policy", ppo, "--steps", 32, "--num-envs", 4, "--out", tmp_path / "traj-ppo")
    assert json.loads(ok("data", "info", tmp_path / "traj-ppo", "--json"))["policies"] == ["run:ppo@256"]
    (result,) = json.loads(ok("eval", run, "--episodes", 4, "--json"))
    assert result["episodes"] == 4 and 0.0 <= result["success_rate"] <= 1.0
    table = ok("eval", run, ppo, "--episodes", 2)
    assert "| ppo | BabyAI-GoToLocal-v0 | 256 |" in table and "actions sampled" in table
    assert len({line.count("|") for line in table.splitlines() if line.startswith("|")}) == 1
    assert len(json.loads(ok("eval", ppo, run, "--episodes", 2, "--json", "--greedy"))) == 2
    table = ok("report", run, ppo, "--every", 128)
    assert "| illm |" in table and "| ppo |" in table


def _no_text(case, env, shape, traj, collected, tmp_path) -> None:
    """A suite without text observations (`collected`: `data info` of `traj`): collected and trained,
    annotate and chibit refused in one line."""
    assert collected["env_ids"] == [case.env]
    refused = runner.invoke(app, ["annotate", str(traj), "--cache", str(tmp_path / "ann")])
    assert refused.exit_code == 1 and "no text observation" in refused.output and "Traceback" not in refused.output
    assert not (tmp_path / "ann").exists()
    for method in case.baselines:
        ok("train", *env, "--method", method, *shape, "--frames", case.frames, "--out", tmp_path / method)
        assert len(metrics(tmp_path / method)) == case.frames // (case.num_envs * case.num_steps)
    table = ok("eval", *(tmp_path / m for m in case.baselines), "--episodes", 2)
    assert "(mean return)" in table and f"| rnd | {case.env} | {case.frames} |" in table
    refused = runner.invoke(app, ["train", "--env", case.env, "--method", "chibit", "--frames", 64, "--out",
                                  str(tmp_path / "chibit")])
    assert refused.exit_code == 1 and "reads grid observations" in refused.output


def test_a_damaged_shard_is_named_and_refused(tmp_path, tiny_lm):
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    ok("collect", "--env", "BabyAI-GoToLocal-v0", "--steps", 16, "--num-envs", 2, "--out", traj)
    ok("annotate", traj, "--cache", ann, "--model", tiny_lm.spec.path, "--dtype", "float32", "--limit", 2,
       "--tasks", "action")
    shard = next(ann.glob("shard-*.arrow"))
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    result = runner.invoke(app, ["cache", "verify", str(ann)])
    assert result.exit_code == 1 and shard.name in result.output
    result = runner.invoke(app, ["cache", "info", str(ann)])
    assert result.exit_code == 1 and "illm cache verify" in result.output


def test_train_without_a_cache_says_what_to_do(tmp_path):
    result = runner.invoke(app, ["train", "--method", "illm", "--frames", 128, "--out", str(tmp_path / "r")])
    assert result.exit_code == 1 and "--cache" in result.output
