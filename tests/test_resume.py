"""Run folders: settings travel with the run on --resume, checkpoints survive damage (the previous
one is kept and used, saying so), a moved folder resumes, and SIGTERM stops a run at an update
boundary with a checkpoint."""

from __future__ import annotations

import json
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from cli.main import app
from illm_tools.errors import DamagedFileError
from illm_tools.rl.checkpoint import load_checkpoint, save_checkpoint
from fakes import flip, truncate

runner = CliRunner()
SMALL = ["--method", "ppo", "--num-envs", "2", "--num-steps", "32"]  # 64 frames per update


def train(*args) -> str:
    out = runner.invoke(app, ["train", *map(str, args)])
    assert out.exit_code == 0, out.output
    return out.output


def updates(run: Path) -> list[int]:
    return [json.loads(line)["update"] for line in (run / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture()
def run(tmp_path) -> Path:
    out = tmp_path / "run"
    train(*SMALL, "--frames", 128, "--seed", 5, "--out", out)
    return out


def test_resume_reads_the_runs_settings_and_refuses_changes_that_alter_learning(run, tmp_path):
    assert "to 256 frames" in train("--out", run, "--resume", "--frames", 256)  # no --method ppo needed
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["method"] == "ppo" and cfg["seed"] == 5 and cfg["total_steps"] == 256 and updates(run) == [1, 2, 3, 4]
    out = runner.invoke(app, ["train", "--out", str(run), "--resume", "--frames", "512", "--seed", "1"])
    assert out.exit_code == 1 and "--seed (the run has 5)" in out.output and "--frames" in out.output
    assert len(out.output.strip().splitlines()) == 1
    assert json.loads((run / "config.json").read_text()) == cfg  # nothing rewritten
    assert "already at 256 frames" in train("--out", run, "--resume", "--frames", 256)
    moved = tmp_path / "elsewhere" / "run"
    shutil.copytree(run, moved)
    assert "to 320 frames" in train("--out", moved, "--resume", "--frames", 320, "--live-budget", 3)
    assert json.loads((moved / "config.json").read_text())["run_dir"] == str(moved)


def test_a_damaged_checkpoint_falls_back_to_the_previous_one_saying_so(run, caplog):
    latest, previous = load_checkpoint(run), torch.load(run / "checkpoint.prev.pt", weights_only=True)
    assert latest["update"] == 2 and previous["format_version"] == 2
    flip(run / "checkpoint.pt", random.Random(0))
    with caplog.at_level("WARNING"):
        state = load_checkpoint(run)
    assert state["update"] == 1 and "using the previous checkpoint" in caplog.text
    assert "to 192 frames" in train("--out", run, "--resume", "--frames", 192)
    assert updates(run) == [1, 2, 3]  # the rows after the checkpoint used were redone
    truncate(run / "checkpoint.pt", random.Random(1))
    truncate(run / "checkpoint.prev.pt", random.Random(2))
    out = runner.invoke(app, ["train", "--out", str(run), "--resume", "--frames", 256])
    assert out.exit_code == 1 and "so is the previous one" in out.output and "Traceback" not in out.output
    out = runner.invoke(app, ["eval", str(run), "--episodes", "2"])
    assert out.exit_code == 1 and "damaged" in out.output and "Traceback" not in out.output


def test_checkpoint_damage_at_random_offsets_is_detected_never_loaded(tmp_path):
    state = {"update": 3, "model": {"w": torch.arange(1000, dtype=torch.float32)}}
    save_checkpoint(tmp_path, state)
    rng = random.Random(7)
    for i in range(8):
        folder = tmp_path / f"c{i}"
        folder.mkdir()
        shutil.copy(tmp_path / "checkpoint.pt", folder / "checkpoint.pt")
        (flip if i % 2 else truncate)(folder / "checkpoint.pt", rng)
        try:
            loaded = load_checkpoint(folder)
        except DamagedFileError as e:
            assert "checkpoint.pt" in str(e) and "\n" not in str(e)
            continue
        assert torch.equal(loaded["model"]["w"], state["model"]["w"])  # a flip in padding changes nothing


def test_a_run_being_trained_elsewhere_is_refused_and_left_alone(run):
    """A second trainer of one folder (a re-submitted cluster job) stops at once: one line, no write."""
    from illm_tools import durable
    from illm_tools.rl.run import RUN_LOCK

    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    with durable.exclusive(run / RUN_LOCK):  # the other trainer, holding the folder
        out = runner.invoke(app, ["train", "--out", str(run), "--resume", "--frames", 256])
    assert out.exit_code == 1 and "is being trained by another process" in out.output
    assert len(out.output.strip().splitlines()) == 1
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    assert "to 256 frames" in train("--out", run, "--resume", "--frames", 256)  # free again: it continues


def test_damaged_config_and_metrics_give_one_line(run):
    metrics = run / "metrics.jsonl"
    lines = metrics.read_text().splitlines()
    metrics.write_text(lines[0] + "\n" + lines[1][:20])  # killed while writing the last row
    assert "to 192 frames" in train("--out", run, "--resume", "--frames", 192)
    lines = metrics.read_text().splitlines()
    metrics.write_text("\n".join([lines[0][:30], *lines[1:]]) + "\n")
    out = runner.invoke(app, ["train", "--out", str(run), "--resume", "--frames", 256])
    assert out.exit_code == 1 and "metrics.jsonl line 1 is damaged" in out.output
    (run / "config.json").write_text('{"mode": "ppo", "env')
    for command in (["eval", str(run), "--episodes", "2"], ["report", str(run)],
                    ["train", "--out", str(run), "--resume"]):
        out = runner.invoke(app, command)
        assert out.exit_code == 1 and "config.json is damaged" in out.output and "Traceback" not in out.output


@pytest.mark.slow
def test_sigterm_stops_training_at_an_update_with_a_checkpoint_and_resume_finishes(tmp_path):
    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "cli.main", "train", *SMALL, "--frames", "100000", "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    start = time.monotonic()
    while not (out / "checkpoint.pt").exists() and proc.poll() is None and time.monotonic() - start < 120:
        time.sleep(0.05)
    time.sleep(random.Random(0).uniform(0.0, 1.0))
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr
    assert "SIGTERM: finishing the current update" in stderr and "Traceback" not in stderr
    frames = int(stdout.split("stopped at ")[1].split()[0].replace(",", ""))
    assert load_checkpoint(out)["global_step"] == frames and updates(out) == list(range(1, frames // 64 + 1))
    assert f"to {frames + 128:,} frames" in train("--out", out, "--resume", "--frames", frames + 128)
    assert updates(out) == list(range(1, frames // 64 + 3))


def test_a_run_written_before_mode_became_method_resumes_and_evaluates(run):
    """config.json of older versions names the method `mode` (`illm_tools.rl.config.RENAMED`)."""
    cfg = json.loads((run / "config.json").read_text())
    cfg["mode"] = cfg.pop("method")
    (run / "config.json").write_text(json.dumps(cfg))
    assert "to 256 frames" in train("--out", run, "--resume", "--frames", 256)
    assert json.loads((run / "config.json").read_text())["method"] == "ppo"
    out = runner.invoke(app, ["eval", str(run), "--episodes", "2"])
    assert out.exit_code == 0, out.output
