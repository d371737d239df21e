"""Choices made per machine: `--dtype auto` (a timed matmul, cached per machine, the resolved dtype
in every key), the heads' dtype recorded in config.json and kept on resume, and a run (or server)
that adopts its cache's setup whatever this machine's auto would choose."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.llm import dtype as dtypes
from illm_tools.tasks.annotation_setup import adopt_model
from fakes import cli_ok as ok

runner = CliRunner()


def test_auto_is_measured_once_per_machine_and_resolves_to_a_concrete_dtype(tmp_path, monkeypatch):
    monkeypatch.setenv("ILLM_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("ILLM_DTYPE_PROBE", raising=False)
    dtypes._measured.cache_clear()
    timed = []
    monkeypatch.setattr(dtypes, "_seconds", lambda dtype, shape: timed.append(str(dtype)) or
                        (1.0 if "bfloat16" in str(dtype) else 2.0))
    assert dtypes.resolve_dtype("auto") == "bfloat16" and len(timed) == 2
    record = json.loads((tmp_path / dtypes.PROBE_FILE).read_text())
    (key, value), = record.items()
    assert dtypes.cpu_signature() in key and value["bf16_faster"] is True
    dtypes._measured.cache_clear()  # a new process: read from the file, not measured again
    assert dtypes.resolve_dtype("auto") == "bfloat16" and len(timed) == 2
    assert dtypes.resolve_dtype("float32") == "float32" and dtypes.resolve_dtype("auto", "cuda") == "bfloat16"
    with pytest.raises(UsageError, match="--dtype must be one of auto"):
        dtypes.resolve_dtype("bf16")
    dtypes._measured.cache_clear()


@pytest.fixture
def traj(tmp_path):
    ok("collect", "--env", "BabyAI-GoToLocal-v0", "--steps", 128, "--num-envs", 2, "--out", tmp_path / "traj")
    return tmp_path / "traj"


def test_the_resolved_dtype_is_in_the_keys_and_the_run_records_its_choices(traj, tmp_path, monkeypatch):
    monkeypatch.setenv("ILLM_DTYPE_PROBE", "float32")  # a machine where float32 is the faster
    ok("annotate", traj, "--cache", tmp_path / "ann", "--backend", "stub", "--history", 0, "--limit", 4)
    assert adopt_model(AnnotationCache(tmp_path / "ann")) == {"backend": "stub", "model": "stub", "dtype": "float32",
                                                              "quant": "none"}  # the keys' fingerprint: float32
    ok("train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--cache", tmp_path / "ann", "--backend", "stub",
       "--history", 0, "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", 0, "--out", tmp_path / "run")
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["llm"]["dtype"] == "float32" and config["bonus"]["heads_bf16"] is False  # resolved, never "auto"
    monkeypatch.setenv("ILLM_DTYPE_PROBE", "bfloat16")  # resumed on a machine that would choose otherwise
    ok("train", "--out", tmp_path / "run", "--frames", 64, "--resume")
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["llm"]["dtype"] == "float32" and config["bonus"]["heads_bf16"] is False


def test_a_run_adopts_its_caches_setup_and_its_live_rows_land_in_it(traj, tmp_path, monkeypatch):
    monkeypatch.setenv("ILLM_DTYPE_PROBE", "bfloat16")  # the annotating machine: bf16
    ok("annotate", traj, "--cache", tmp_path / "ann", "--backend", "stub", "--history", 0, "--limit", 4)
    monkeypatch.setenv("ILLM_DTYPE_PROBE", "float32")  # the training machine would choose float32
    said = ok("train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--cache", tmp_path / "ann",
              "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", 8, "--live-mode", "sync",
              "--out", tmp_path / "run")
    assert "adopting the cache's setup: --backend stub --model stub --dtype bfloat16 --quant none --history 0 " \
           "--layout shared (4 states answered for every task" in said
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert (config["llm"]["backend"], config["llm"]["dtype"], config["setup"]["history_len"]) == ("stub", "bfloat16", 0)
    setups = AnnotationCache(tmp_path / "ann").setups()
    assert len({s["model_fingerprint"] for s in setups}) == 1 and sum(s["entries"] for s in setups) > 8  # live rows

    ok("annotate", traj, "--cache", tmp_path / "ann", "--backend", "oracle", "--history", 0, "--limit", 4)
    refused = runner.invoke(app, ["train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--cache",
                                  str(tmp_path / "ann"), "--frames", 32, "--out", str(tmp_path / "run2")])
    assert refused.exit_code == 1 and "holds 2 setups for the tasks action,summary" in refused.output
    assert "--backend oracle --history 0 --layout shared" in refused.output
    assert "--backend stub --model stub --dtype bfloat16" in refused.output and "Traceback" not in refused.output
    given = ok("train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--cache", tmp_path / "ann", "--backend",
               "oracle", "--history", 0, "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", 0,
               "--out", tmp_path / "run3")
    assert "adopting" not in given  # options given: no adoption


def test_a_server_adopts_its_caches_model_setup(traj, tmp_path, monkeypatch):
    monkeypatch.setenv("ILLM_DTYPE_PROBE", "bfloat16")
    assert adopt_model(AnnotationCache(tmp_path / "empty")) is None
    ok("annotate", traj, "--cache", tmp_path / "ann", "--backend", "stub", "--model", "stub:32", "--history", 0,
       "--limit", 2)
    assert adopt_model(AnnotationCache(tmp_path / "ann")) == {"backend": "stub", "model": "stub:32",
                                                              "dtype": "bfloat16", "quant": "none"}
    ok("annotate", traj, "--cache", tmp_path / "ann", "--backend", "oracle", "--history", 0, "--limit", 2)
    with pytest.raises(UsageError, match="holds annotations of 2 model setups: .*--backend oracle"):
        adopt_model(AnnotationCache(tmp_path / "ann"))
