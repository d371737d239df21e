"""Multi-process annotation: `accelerate launch --multi_gpu --num_processes 2 -m cli.main annotate`
(torchrun; CPU processes here) and `illm annotate --num-processes 2` split the plan's states
between two processes, each writing its own shards through the cache's lock, and give the cache
one process gives: the same keys, the same answers (scores equal up to float rounding of other
batchings), nothing twice. `accelerate launch --cpu --num_processes 2` (one process without MPI)
gives it too."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.cache import AnnotationCache, verify

runner = CliRunner()
pytestmark = [pytest.mark.usefixtures("model_cache_in_tmp"), pytest.mark.slow]


def rows_of(cache_dir):
    import pyarrow as pa

    from illm_tools.cache import layout

    manifest = layout.read_manifest(cache_dir)
    table = pa.concat_tables([layout.read_shard(cache_dir / s["name"]) for s in manifest["shards"]])
    return {r["key"]: r for r in table.to_pylist()}


def told(done) -> str:
    """A failed launch's own words: the head of its stderr (where a process's error is) and the tail
    (the launcher's summary), without the launcher's traceback in between."""
    err = done.stderr
    return err if len(err) < 4000 else f"{err[:2500]}\n...\n{err[-1500:]}"


def test_two_processes_give_the_one_process_cache(tmp_path, tiny_lm):
    traj = tmp_path / "traj"
    out = runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", 80, "--num-envs", 4,
                              "--out", str(traj)])
    assert out.exit_code == 0, out.output
    common = ["--model", tiny_lm.spec.path, "--dtype", "float32", "--history", "0", "--limit", "12",
              "--batch-size", "4"]
    one = runner.invoke(app, ["annotate", str(traj), "--cache", str(tmp_path / "one"), *common])
    assert one.exit_code == 0, one.output
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "PYTHONWARNINGS": "ignore"}
    launch = [sys.executable, "-m", "accelerate.commands.launch", "--num_processes", "2", "--num_machines", "1",
              "--mixed_precision", "no", "--dynamo_backend", "no", "-m", "cli.main", "annotate", str(traj)]
    launched = subprocess.run([*launch[:3], "--multi_gpu", *launch[3:], "--cache", str(tmp_path / "two"), *common],
                              capture_output=True, text=True, env=env, timeout=300)
    assert launched.returncode == 0, told(launched)
    assert launched.stdout.count("annotated 12 states (24 rows") == 1  # one report, the counts of both processes
    cpu = subprocess.run([*launch[:3], "--cpu", *launch[3:], "--cache", str(tmp_path / "cpu"), *common],
                         capture_output=True, text=True, env=env, timeout=300)
    assert cpu.returncode == 0, told(cpu)
    shortcut = subprocess.run([sys.executable, "-m", "cli.main", "annotate", str(traj), "--cache",
                               str(tmp_path / "short"), *common, "--num-processes", "2"],
                              capture_output=True, text=True, env=env, timeout=300)
    assert shortcut.returncode == 0, told(shortcut)
    reference = rows_of(tmp_path / "one")
    for name in ("two", "short", "cpu"):
        report = verify(tmp_path / name)
        assert report.ok and report.rows == len(reference) == 24
        assert report.shards >= (2 if name != "cpu" else 1)  # both processes wrote shards of their own
        rows = rows_of(tmp_path / name)
        assert rows.keys() == reference.keys()
        for key, row in rows.items():
            ref = reference[key]
            if row["task"] == "action":
                assert np.allclose(row["cand_logprob_sum"], ref["cand_logprob_sum"], atol=1e-4)
            else:
                assert row["text"] == ref["text"]
                assert np.allclose(row["embedding"], ref["embedding"], atol=1e-4)
    assert len(AnnotationCache(tmp_path / "two")) == 24
