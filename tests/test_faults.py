"""Damaged files: every file kind illm reads back, cut short or with a flipped bit at random
offsets, gives one line naming it (a typed error; on the CLI exit code 1, no traceback) or a
verified recovery, and never silently other data; nothing on disk is overwritten."""

from __future__ import annotations

import json
import os
import random
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.cache.store import AnnotationCache
from illm_tools.data.trajectories import TrajectoryWriter, open_table
from illm_tools.errors import CacheError, DamagedFileError, IllmError
from fakes import flip, trajectory_rows as rows, truncate

runner = CliRunner()
OFFSETS = 6  # random offsets tried per file and damage kind (seeded)




def damaged_copies(src, tmp_path, name: str):
    """(damage kind, folder) copies of `src` with file `name` damaged at random offsets."""
    rng = random.Random(f"{name}")
    for kind, damage in (("truncated", truncate), ("bit flip", flip)):
        for i in range(OFFSETS):
            dst = tmp_path / f"{name.replace('/', '_')}-{kind.replace(' ', '_')}-{i}"
            shutil.copytree(src, dst)
            damage(dst / name, rng)
            yield kind, dst


@pytest.fixture()
def trajectories(tmp_path):
    out = tmp_path / "traj"
    with TrajectoryWriter(out, shard_rows=6) as w:
        w.add(rows(10, 0))
        w.add(rows(5, 1))
    return out


def test_a_damaged_trajectory_shard_or_state_is_refused_never_read_as_other_data(trajectories, tmp_path):
    shard = json.loads((trajectories / "state.json").read_text())["_data_files"][0]["filename"]
    intact = open_table(trajectories)
    for name in (shard, "state.json"):
        for kind, folder in damaged_copies(trajectories, tmp_path, name):
            try:
                table = open_table(folder)
            except IllmError as e:
                assert name in str(e) and ("re-collect" in str(e) or "illm collect" in str(e)), (kind, str(e))
                continue
            assert table.equals(intact), f"{kind} of {name} was read as other data"  # e.g. whitespace in JSON


def test_data_info_and_annotate_give_one_line_for_a_damaged_dataset(trajectories, tmp_path):
    shard = json.loads((trajectories / "state.json").read_text())["_data_files"][1]["filename"]
    truncate(trajectories / shard, random.Random(0))
    out = runner.invoke(app, ["data", "info", str(trajectories)])
    assert out.exit_code == 1 and "Traceback" not in out.output
    assert out.output.count("\n") == 1 and shard in out.output and "damaged" in out.output
    cache = tmp_path / "ann"
    out = runner.invoke(app, ["annotate", str(trajectories), "--cache", str(cache), "--model", "smollm2-135m"])
    assert out.exit_code == 1 and "Traceback" not in out.output and shard in out.output
    assert not cache.exists()  # nothing written


def test_damaged_dataset_info_is_named_by_data_info(trajectories):
    (trajectories / "dataset_info.json").write_text('{"citation": "", "feat')
    out = runner.invoke(app, ["data", "info", str(trajectories)])
    assert out.exit_code == 1 and "dataset_info.json" in out.output and "Traceback" not in out.output
    assert open_table(trajectories).num_rows == 15  # illm itself does not need it


def _cache(tmp_path):
    cache = AnnotationCache(tmp_path / "ann")
    for part in range(2):
        cache.write([{"key": f"{'%064x' % (part * 10 + i)}", "task": "summary", "template_version": 1,
                      "renderer": "r@1", "model": "m", "model_fingerprint": "f", "decoding": "{}", "history_len": 0,
                      "goal": "g", "history": "h", "observation": "o", "prompt": "p", "candidates": None,
                      "cand_token_logprobs": None, "cand_logprob_sum": None, "cand_token_count": None,
                      "neutral_logprob_sum": None, "chosen_index": None, "text": "t",
                      "embedding": [float(i), 1.0], "embedding_dim": 2, "created_unix": 0.0} for i in range(4)])
    return cache.root


def test_a_damaged_cache_shard_or_manifest_is_refused_never_read_as_other_data(tmp_path):
    from illm_tools.cache.verify import verify

    root = _cache(tmp_path)
    keys = ["%064x" % k for k in (0, 1, 2, 3, 10, 11, 12, 13)]
    intact = AnnotationCache(root).get_columns(keys, ["embedding"])["embedding"]
    manifest = json.loads((root / "manifest.json").read_text())
    for name in (manifest["shards"][0]["name"], "manifest.json"):
        for kind, folder in damaged_copies(root, tmp_path, name):
            try:
                got = AnnotationCache(folder).get_columns(keys, ["embedding"])["embedding"]
            except (CacheError, IllmError) as e:
                assert str(e).strip() and "\n" not in str(e).strip(), (kind, str(e))
                continue
            assert np.array_equal(got, intact, equal_nan=True), f"{kind} of {name} was read as other data"
            assert verify(folder).ok or name == "manifest.json"


@pytest.mark.slow
def test_a_damaged_model_cache_entry_is_refused_saying_to_delete_it(smollm2_cache, tmp_path):
    from illm_tools.llm.loading import load_model

    load_model("smollm2-135m", dtype="float32", cache_dir=smollm2_cache)  # de-quantised once per test run
    (entry,) = (smollm2_cache / "models").iterdir()
    rng = random.Random(0)
    for name, damage in (("model.safetensors", flip), ("config.json", truncate), ("illm_source.json", truncate)):
        root = tmp_path / name
        copy = root / "models" / entry.name
        shutil.copytree(entry, copy, copy_function=os.link)  # links: loading reads an entry, never writes it
        (copy / name).unlink()
        shutil.copyfile(entry / name, copy / name)  # the damaged file alone is a copy of its own
        damage(copy / name, rng)
        with pytest.raises(DamagedFileError, match=f"{entry.name} is damaged.*rm -r"):
            load_model("smollm2-135m", dtype="float32", cache_dir=root)


def test_a_damaged_metrics_csv_is_refused_by_report_naming_the_line(tmp_path):
    from fakes import fake_run

    run = tmp_path / "run"
    fake_run(run, 0, [(50 * i, 0.5, 1) for i in range(1, 9)])
    intact = runner.invoke(app, ["report", str(run), "--every", "100", "--json"])
    assert intact.exit_code == 0
    rng = random.Random(1)
    for i in range(OFFSETS):
        copy = tmp_path / f"copy{i}"
        shutil.copytree(run, copy)
        text = (copy / "metrics.csv").read_text()
        header = len(text.splitlines()[0]) + 1
        (copy / "metrics.csv").write_text(text[:rng.randrange(header + 1, len(text) - 1)])  # cut inside the rows
        out = runner.invoke(app, ["report", str(copy), "--every", "100", "--json"])
        if out.exit_code == 0:  # cut at a line end: a shorter run, whose rows are the intact ones
            short, whole = json.loads(out.output)[0], json.loads(intact.output)[0]
            full = short["frames"][:-1]  # its last window may be a shorter one of its own
            assert full == whole["frames"][:len(full)] and short["mean"][:len(full)] == whole["mean"][:len(full)]
            continue
        assert out.exit_code == 1 and "metrics.csv" in out.output and "Traceback" not in out.output


def _annotate_cmd(trajectories, cache, model) -> list[str]:
    """Chunks of 8 states: many shards from a small dataset, so a signal lands with work still to do."""
    import sys

    return [sys.executable, "-m", "cli.main", "annotate", str(trajectories), "--cache", str(cache), "--model", model,
            "--dtype", "float32", "--history", "0", "--batch-size", "2", "--chunk", "8"]


def _wait_for_shards(cache, proc, n: int = 1, timeout: float = 120.0) -> None:
    import time

    start = time.monotonic()
    while time.monotonic() - start < timeout and proc.poll() is None:
        manifest = cache / "manifest.json"
        if manifest.is_file() and len(json.loads(manifest.read_text())["shards"]) >= n:
            return
        time.sleep(0.05)


@pytest.fixture(scope="module")
def annotated_whole(tmp_path_factory, tiny_lm):
    """The trajectories the signal tests annotate, and their cache annotated in one go by a process no signal
    reached: the reference an interrupted and rerun cache must equal (made once for both tests)."""
    import subprocess
    from pathlib import Path

    from conftest import collect_babyai

    trajectories = collect_babyai(tmp_path_factory, steps=160, seed=3, action_space="original")
    whole = tmp_path_factory.mktemp("whole") / "ann"
    env = {**os.environ, "ILLM_CACHE_DIR": str(tmp_path_factory.mktemp("illm-cache"))}
    subprocess.run(_annotate_cmd(trajectories, whole, tiny_lm.spec.path), cwd=Path(__file__).resolve().parents[1],
                   check=True, capture_output=True, env=env)
    return trajectories, whole


@pytest.mark.slow
@pytest.mark.xdist_group("sigterm-annotate")  # one worker makes `annotated_whole` once for both
@pytest.mark.parametrize("signals", [1, 2])
def test_sigterm_during_annotate_keeps_whole_chunks_and_a_rerun_finishes_the_same_cache(
        signals, tmp_path, annotated_whole, tiny_lm, model_cache_in_tmp):
    import signal
    import subprocess
    from pathlib import Path

    from illm_tools.cache.verify import verify

    trajectories, whole = annotated_whole
    repo = Path(__file__).resolve().parents[1]
    cache = tmp_path / "ann"
    proc = subprocess.Popen(_annotate_cmd(trajectories, cache, tiny_lm.spec.path), cwd=repo,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_shards(cache, proc)
    for _ in range(signals):
        proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, (proc.returncode, err)
    assert "Traceback" not in err
    if signals == 1:
        assert "SIGTERM: finishing the chunk in progress" in err and "stopped by a signal" in out
    report = verify(cache)
    assert report.ok, report.problems  # listed shards whole; a second signal may leave an unlisted one
    rerun = subprocess.run(_annotate_cmd(trajectories, cache, tiny_lm.spec.path), cwd=repo, capture_output=True,
                           text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    done, reference = AnnotationCache(cache), AnnotationCache(whole)
    assert len(done) == len(reference)
    keys = reference._distinct(["key"]).column("key").to_pylist()
    assert done.contains(keys).all()
    a = done.get_columns(keys, ["embedding", "cand_logprob_sum"])
    b = reference.get_columns(keys, ["embedding", "cand_logprob_sum"])
    assert np.allclose(a["embedding"], b["embedding"], equal_nan=True) and a["cand_logprob_sum"] == b["cand_logprob_sum"]


def test_cache_verify_and_repair_agree_on_one_path_to_a_usable_cache(tmp_path):
    root = _cache(tmp_path)
    shards = [s["name"] for s in json.loads((root / "manifest.json").read_text())["shards"]]
    flip(root / shards[0], random.Random(3))
    out = runner.invoke(app, ["cache", "verify", str(root)])
    assert out.exit_code == 1 and f"illm cache repair {root} --drop-damaged" in out.output
    out = runner.invoke(app, ["cache", "repair", str(root)])
    assert out.exit_code == 1 and "--drop-damaged" in out.output and "Traceback" not in out.output
    assert (root / shards[0]).is_file()  # nothing moved without the flag
    out = runner.invoke(app, ["cache", "repair", str(root), "--drop-damaged"])
    assert out.exit_code == 0, out.output
    assert "dropped 1 damaged shards (4 entries" in out.output and out.output.rstrip().endswith("ok")
    assert (root / "damaged" / shards[0]).is_file() and not (root / shards[0]).exists()
    cache = AnnotationCache(root)
    assert len(cache) == 4 and cache.contains(["%064x" % 10]).all()
    assert runner.invoke(app, ["cache", "verify", str(root)]).exit_code == 0


def test_repair_rebuilds_an_unreadable_manifest_from_the_shards(tmp_path):
    root = _cache(tmp_path)
    keys = ["%064x" % k for k in (0, 1, 2, 3, 10, 11, 12, 13)]
    intact = AnnotationCache(root).get_columns(keys, ["embedding"])["embedding"]
    truncate(root / "manifest.json", random.Random(4))
    out = runner.invoke(app, ["cache", "info", str(root)])
    assert out.exit_code == 1 and "Traceback" not in out.output
    out = runner.invoke(app, ["cache", "repair", str(root), "--drop-damaged"])
    assert out.exit_code == 0, out.output
    assert "manifest was unreadable" in out.output and "adopted 2" in out.output
    assert np.array_equal(AnnotationCache(root).get_columns(keys, ["embedding"])["embedding"], intact)
    assert list((root / "damaged").iterdir())[0].name.startswith("manifest.json.")


def _disk_full_after(half: bool):
    """`illm_tools.durable.staged` whose file takes part of the data, then fails as a full disk does."""
    import contextlib
    import errno

    from illm_tools import durable

    real = durable.staged

    @contextlib.contextmanager
    def staged(path, mode="wb", *, tmp=None):
        with real(path, mode, tmp=tmp) as fh:
            class Full:
                name = fh.name

                def write(self, data):
                    fh.write(data[:len(data) // 2] if half else b"")
                    raise OSError(errno.ENOSPC, "No space left on device", str(fh.name))

            yield Full()

    return staged


def test_a_full_disk_midway_leaves_the_cache_and_the_run_folder_readable(tmp_path, monkeypatch):
    import errno

    from cli.errors import report
    from illm_tools import durable
    from illm_tools.cache.verify import verify
    from illm_tools.rl.checkpoint import CheckpointWriter, load_checkpoint, save_checkpoint

    root = _cache(tmp_path)
    before = sorted(p.name for p in root.iterdir())
    row = AnnotationCache(root).lookup(["%064x" % 0])["%064x" % 0]
    monkeypatch.setattr(durable, "staged", _disk_full_after(half=True))
    with pytest.raises(OSError) as err:
        AnnotationCache(root).write([{**row, "key": "%064x" % 99}])
    monkeypatch.undo()
    assert err.value.errno == errno.ENOSPC and report(err.value) == 1
    assert sorted(p.name for p in root.iterdir()) == before and verify(root).ok and len(AnnotationCache(root)) == 8

    save_checkpoint(tmp_path, {"update": 1})
    save_checkpoint(tmp_path, {"update": 2})

    def full(obj, fh):
        fh.write(b"\x80\x02partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    import io

    import torch

    real_save = torch.save  # the state is serialised in memory first; the file write fails
    monkeypatch.setattr(torch, "save", lambda obj, f: real_save(obj, f) if isinstance(f, io.BytesIO) else full(obj, f))
    with pytest.raises(OSError):
        save_checkpoint(tmp_path, {"update": 3})
    writer = CheckpointWriter(tmp_path)  # the trainer's: the write goes on beside the training, its error comes after
    writer.save({"update": 4}, wait=False)
    with pytest.raises(OSError):
        writer.wait()
    monkeypatch.undo()
    assert load_checkpoint(tmp_path)["update"] == 2 and not list(tmp_path.glob(".checkpoint.pt.tmp"))
    writer.save({"update": 5}, wait=False)
    writer.wait()
    assert load_checkpoint(tmp_path)["update"] == 5



def test_a_test_run_without_room_for_its_folders_stops_at_once_with_one_line():
    """tests/conftest.py's check: with too little disk free for the tests' temporary folders the run stops
    before its first test, with exit code 1 and a line that says what to free (not, minutes in, with
    tests failing at random on `No space left on device`, as a CI run did)."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import collections, shutil, sys, pytest\n"
            "shutil.disk_usage = lambda path: collections.namedtuple('Usage', 'total used free')(10**10, 10**10, 5 * 10**8)\n"
            "sys.exit(pytest.main(['-q', '-p', 'no:cacheprovider', 'tests/test_layers.py']))\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_XDIST")}  # a run of its own, not a worker
    out = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1
    assert "only 0.5 GB free" in out.stdout and "free some" in out.stdout and "passed" not in out.stdout
    assert "Traceback" not in out.stdout + out.stderr
