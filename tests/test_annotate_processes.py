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


LEAVE = """
import os, sys, time

def gloo_threads():
    names = []
    for t in os.listdir("/proc/self/task"):
        try:
            names.append(open(f"/proc/self/task/{t}/comm").read().strip())
        except OSError:  # ended meanwhile
            pass
    return sorted(n for n in names if "gloo" in n)

from accelerate.utils import gather_object
from illm_tools.annotate.bulk import distributed_state

state = distributed_state()
import torch.distributed.fsdp  # what transformers imports when it loads a model, the group made
with state.split_between_processes(list(range(12))) as mine:
    list(mine)
gather_object([state.process_index])
state.wait_for_everyone()
assert gloo_threads(), "no gloo thread by these names: the check below would see nothing"
state.destroy_process_group()
deadline = time.monotonic() + 60  # a joined thread leaves /proc/self/task a moment after its join
while gloo_threads() and time.monotonic() < deadline:
    time.sleep(0.05)
print(f"rank {os.environ['RANK']}: gloo threads left after destroy_process_group: {gloo_threads()}", flush=True)
sys.exit(1 if gloo_threads() else 0)
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="reads thread names from /proc (Linux)")
def test_destroyed_group_leaves_no_gloo_threads(tmp_path):
    """A process leaves with its gloo group gone, threads and all: a group something still holds
    (torch.distributed.nn binds it into its functions' defaults when imported after the group is
    made, as transformers does) keeps its worker threads into interpreter shutdown, where one can
    abort the process (`terminate called without an active exception`, SIGABRT) after its work is done."""
    script = tmp_path / "leave.py"
    script.write_text(LEAVE)
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           str(script)], capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stdout + told(done)
    assert done.stdout.count("gloo threads left after destroy_process_group: []") == 2, done.stdout
