"""`illm experiment`: spec parsing and validation (bad specs refused naming the line, before any
run), the shipped specs all plan, and a partly finished grid resumes: finished runs skipped,
unfinished ones resumed, new ones started."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.errors import UsageError
from illm_tools.experiment import load_spec, plan

runner = CliRunner()
SPECS = sorted((Path(__file__).resolve().parents[1] / "experiments" / "specs").glob("*.yaml"))
TINY = """\
name: tiny
frames: 64
seeds: 2
envs: [BabyAI-GoToLocal-v0]
methods: [ppo]
grid:
  num_dists: [1, 2]
settings:
  num_envs: 2
  num_steps: 16
  num_minibatches: 2
  tensorboard: false
"""


def write(tmp_path, text, name="spec.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("spec", SPECS, ids=lambda p: p.stem)
def test_every_shipped_spec_plans(spec, tmp_path):
    runs = plan(load_spec(spec), tmp_path / "results")
    assert runs and all(r.status == "new" for r in runs)
    assert len({r.config.run_dir for r in runs}) == len(runs)


@pytest.mark.parametrize("text,message", [
    (TINY.replace("methods: [ppo]", "methods: [ppo, rdn]"), "line 5: unknown method 'rdn'"),
    (TINY.replace("envs: [BabyAI-GoToLocal-v0]", "envs: [BabyAI-GoToLocl-v0]"), "line 4: unknown environment id"),
    (TINY.replace("  num_envs: 2", "  num_env: 2"), "line 9: unknown setting 'num_env' (did you mean num_envs?)"),
    (TINY.replace("grid:", "gird:"), "line 6: unknown key 'gird' (did you mean grid?)"),
    (TINY.replace("  num_dists: [1, 2]", "  num_dists: 3"), "line 7: grid.num_dists must be a non-empty list"),
    (TINY.replace("  num_steps: 16", "  num_steps: -1"), "--num-steps must be positive"),
    (TINY.replace("  num_envs: 2", "  seed: 2"), "line 9: seed is set by the grid itself"),
    (TINY + "  num_dists: [: bad\n", "is not valid YAML"),
    (TINY.replace("envs: [BabyAI-GoToLocal-v0]", "envs: []"), "needs a non-empty 'envs' list"),
    (TINY + "cluster:\n  cpu: 2\n", "line 14: cluster takes partition, time_minutes, cpus, gpus, mem_gb"),
    (TINY + "cluster:\n  cpus: 0\n", "line 13: cluster: --cpus must be positive"),
])
def test_bad_specs_are_refused_naming_the_line_before_anything_runs(tmp_path, text, message):
    spec = write(tmp_path, text)
    out = runner.invoke(app, ["experiment", str(spec), "--out", str(tmp_path / "results")])
    assert out.exit_code == 1 and message in out.output and "Traceback" not in out.output, out.output
    assert not (tmp_path / "results").exists()
    with pytest.raises(UsageError):
        plan(load_spec(spec), tmp_path / "r")


@pytest.mark.slow
def test_a_partly_finished_grid_skips_resumes_and_starts(tmp_path):
    spec, results = write(tmp_path, TINY), tmp_path / "results"
    runs = plan(load_spec(spec), results)
    assert [r.label for r in runs] == ["ppo-num_dists=1"] * 2 + ["ppo-num_dists=2"] * 2
    # one run finished, one stopped half way, by hand
    first, second = runs[0].config.run_dir, runs[1].config.run_dir
    base = ["train", "--env", "BabyAI-GoToLocal-v0", "--method", "ppo", "--num-dists", 1, "--num-envs", 2,
            "--num-steps", 16, "--num-minibatches", 2, "--no-tensorboard", "--threads", 1]
    for run_dir, seed, frames in ((first, 0, 64), (second, 1, 32)):
        out = runner.invoke(app, [str(a) for a in [*base, "--seed", seed, "--frames", frames, "--out", run_dir]])
        assert out.exit_code == 0, out.output
    (results / "spec.yaml").write_text(TINY)
    out = runner.invoke(app, ["experiment", str(spec), "--out", str(results), "--dry-run"])
    assert "1 finished, 1 to resume, 2 to start" in out.output
    out = runner.invoke(app, ["experiment", str(spec), "--out", str(results), "--jobs", "2"])
    assert out.exit_code == 0, out.output
    for run in runs:
        rows = [json.loads(line) for line in (run.config.run_dir / "metrics.jsonl").read_text().splitlines()]
        assert [r["global_step"] for r in rows] == [32, 64]  # the stopped one went on from its checkpoint
    again = runner.invoke(app, ["experiment", str(spec), "--out", str(results)])
    assert "4 finished, 0 to resume, 0 to start" in again.output
    other = write(tmp_path, TINY.replace("seeds: 2", "seeds: 3"), "other.yaml")
    refused = runner.invoke(app, ["experiment", str(other), "--out", str(results)])
    assert refused.exit_code == 1 and "holds the results of another spec" in refused.output


@pytest.mark.parametrize("args,message", [
    (["--launcher", "pbs"], "--launcher must be one of local, slurm, submitit-local"),
    (["--launcher", "slurm", "--cpus", "0"], "--cpus must be positive"),
    (["--launcher", "slurm", "--time-minutes", "-5"], "--time-minutes must be positive"),
])
def test_bad_launcher_settings_are_refused_before_anything_runs(tmp_path, args, message):
    out = runner.invoke(app, ["experiment", str(write(tmp_path, TINY)), "--out", str(tmp_path / "results"), *args])
    assert out.exit_code == 1 and message in out.output and len(out.output.strip().splitlines()) == 1, out.output
    assert not (tmp_path / "results").exists()


@pytest.mark.slow
def test_the_submitit_launcher_runs_a_grid_as_jobs_and_resumes_it(tmp_path):
    """--launcher submitit-local is the SLURM path (submitit job arrays, one run a job) on this
    machine: every run finishes, a second call skips them, a lost run is trained again."""
    pytest.importorskip("submitit")
    spec, results = write(tmp_path, TINY.replace("  num_dists: [1, 2]", "  num_dists: [1]")), tmp_path / "results"
    command = ["experiment", str(spec), "--out", str(results), "--launcher", "submitit-local", "--jobs", "2",
               "--time-minutes", "10"]
    out = runner.invoke(app, command)
    assert out.exit_code == 0 and "all 2 runs finished" in out.output, out.output
    runs = plan(load_spec(spec), results)
    assert all(r.status == "done" for r in runs) and list((results / ".submitit").iterdir())
    assert "2 finished, 0 to resume, 0 to start" in runner.invoke(app, command).output
    lost = runs[1].config.run_dir
    for p in lost.iterdir():
        p.unlink() if p.is_file() else None
    again = runner.invoke(app, command)
    assert "1 finished, 0 to resume, 1 to start" in again.output and again.exit_code == 0, again.output
    assert json.loads((lost / "metrics.jsonl").read_text().splitlines()[-1])["global_step"] == 64


def test_a_method_grid_crosses_values_for_that_method_alone(tmp_path):
    spec = write(tmp_path, TINY.replace("methods: [ppo]", "methods: [ppo, illm]") + """\
method_grid:
  illm: {oracle_noise: [0, 0.5]}
method_settings:
  illm: {backend: oracle, cache: data/ann, history_len: 0, live_budget: all, live_mode: sync}
""")
    runs = plan(load_spec(spec), tmp_path / "results")
    labels = sorted({r.label for r in runs})
    assert labels == ["illm-num_dists=1-oracle_noise=0", "illm-num_dists=1-oracle_noise=0.5",
                      "illm-num_dists=2-oracle_noise=0", "illm-num_dists=2-oracle_noise=0.5",
                      "ppo-num_dists=1", "ppo-num_dists=2"]
    noisy = [r.config for r in runs if r.label.endswith("oracle_noise=0.5")]
    assert noisy and all(c.llm.model == "oracle:noise=0.5" and c.targets.live_budget == "all" for c in noisy)
    bad = write(tmp_path, TINY + "method_grid:\n  rnd: {lambda_a: [1]}\n", "bad.yaml")
    with pytest.raises(UsageError, match="line 14: method_grid names 'rnd', which is not among the spec's methods"):
        plan(load_spec(bad), tmp_path / "r2")


METHOD_SETTINGS = ("layout", "action_target", "reward_streams", "live_budget")
"""How the method is run, where the toolkit may depart from the paper's Algorithm 1 and B.2 (issue 28):
the prompt layout, f^a's target, the reward streams and the live budget. A spec of an iLLM table names
the paper's value of each in its `paper:` block, and says why where it differs."""


def _value(cfg, key: str):
    """A run's value of a paper setting: the model as served, an env option, or the field."""
    if key == "model":
        return cfg.llm.model
    if key.startswith("env_options."):
        return cfg.env_options.get(key.split(".", 1)[1], 0.0)
    value = cfg.flat()[key]
    return "+".join(value) if key == "tasks" else value


@pytest.mark.parametrize("spec", [s for s in SPECS if "\npaper:" in s.read_text()], ids=lambda p: p.stem)
def test_a_spec_sets_what_the_paper_sets_or_says_why_not(spec, tmp_path):
    """Each table's spec records the paper's setting (`paper:`): its rows, grid values, envs, frames,
    seeds and settings. Where the spec does not list a reason under `differs`, it must set the same;
    where it does, it must really differ (no stale reasons)."""
    loaded = load_spec(spec)
    paper = dict(loaded.paper)
    differs = paper.pop("differs", {})
    source, methods, envs, grid = paper.pop("source"), paper.pop("methods"), paper.pop("envs", None), paper.pop("grid", {})
    method_grid = paper.pop("method_grid", {})
    grid_keys = {*grid, *(k for g in method_grid.values() for k in g)}
    assert source and set(differs) <= {"methods", "envs", "frames", "seeds", *grid_keys, *paper}, differs
    runs = [r for r in plan(loaded, tmp_path / "results") if r.config.method in methods]

    def same(key: str, equal: bool) -> None:
        assert equal != (key in differs), f"{spec.name}: {key} {'differs without a reason' if not equal else 'is listed as differing but is the same'}"

    same("methods", set(methods) <= set(loaded.methods))
    if envs is not None:
        same("envs", set(envs) == set(loaded.envs))
    same("frames", loaded.frames == paper.pop("frames"))
    same("seeds", len(loaded.seeds) == paper.pop("seeds"))
    for key, values in grid.items():
        same(key, {str(_value(r.config, key)) for r in runs} == {str(v) for v in values})
    for method, values_of in method_grid.items():
        for key, values in values_of.items():
            same(key, {str(_value(r.config, key)) for r in runs if r.config.method == method} == {str(v) for v in values})
    if any(m.startswith("illm") for m in methods):  # the method's own settings, named in every iLLM spec
        assert set(METHOD_SETTINGS) <= set(paper), f"{spec.name}: paper: names none of {set(METHOD_SETTINGS) - set(paper)}"
    for key, value in paper.items():
        # the LLM's and the bonus's settings, compared where the run reads targets (ppo's are unused defaults)
        of = [r for r in runs if r.config.needs_targets] if key in METHOD_SETTINGS else runs
        same(key, all(_value(r.config, key) == value for r in of))


def test_a_dry_run_names_the_models_this_machine_cannot_load(tmp_path, monkeypatch):
    """Runs of a model no offline copy exists of are named with their count before the grid starts;
    ppo runs, which load no model, are not counted."""
    from illm_tools.llm import registry

    real = registry.list_models()
    monkeypatch.setattr(registry, "list_models", lambda: [*real, registry.ModelInfo(
        "far-away", "hub", "nobody/far-away", False, "not in the hub cache", "")])
    spec = tmp_path / "s.yaml"
    spec.write_text("name: s\nframes: 64\nseeds: 2\nenvs: [BabyAI-GoToLocal-v0]\nmethods: [ppo, illm]\n"
                    "grid: {model: [far-away]}\nsettings: {num_envs: 2, num_steps: 16, num_minibatches: 2, "
                    "cache: " + str(tmp_path / "ann") + "}\n")
    result = CliRunner().invoke(app, ["experiment", str(spec), "--out", str(tmp_path / "r"), "--dry-run"])
    assert result.exit_code == 0, result.output
    assert "not loadable on this machine offline" in result.output and "far-away (2 runs)" in result.output
    assert not (tmp_path / "r").exists()


def test_env_frames_give_a_level_its_own_frames(tmp_path):
    text = TINY.replace("envs: [BabyAI-GoToLocal-v0]", "envs: [BabyAI-GoToLocal-v0, BabyAI-UnlockLocal-v0]")
    spec = write(tmp_path, text + "env_frames:\n  BabyAI-UnlockLocal-v0: 128\n")
    frames = {r.env_id: r.config.total_steps for r in plan(load_spec(spec), tmp_path / "results")}
    assert frames == {"BabyAI-GoToLocal-v0": 64, "BabyAI-UnlockLocal-v0": 128}
    # --frames sets every run's frames, env_frames included
    assert {r.config.total_steps for r in plan(load_spec(spec, frames=32), tmp_path / "r2")} == {32}
    out = runner.invoke(app, ["experiment", str(spec), "--out", str(tmp_path / "r3"), "--dry-run"])
    assert out.exit_code == 0 and "64 to 128 frames per run" in out.output
    for bad, message in (("  BabyAI-GoToObj-v0: 128\n", "line 14: env_frames names 'BabyAI-GoToObj-v0', which is not"),
                         ("  BabyAI-UnlockLocal-v0: -5\n", "line 14: env_frames.BabyAI-UnlockLocal-v0 must be a positive")):
        path = write(tmp_path, text + "env_frames:\n" + bad, "bad.yaml")
        with pytest.raises(UsageError, match=message):
            load_spec(path)


@pytest.mark.parametrize("name", ["suite-tune", "suite-calibration", "suite-calibration-2", "suite-report",
                                  "suite-report-lava"])
def test_the_suite_specs_validate_with_a_dry_run(tmp_path, name):
    """The positive-control suite's specs (issue 28) plan every run, each level at its own frames."""
    spec = Path(__file__).resolve().parents[1] / "experiments" / "specs" / f"{name}.yaml"
    out = runner.invoke(app, ["experiment", str(spec), "--out", str(tmp_path / "r"), "--dry-run"])
    assert out.exit_code == 0, out.output
    runs = plan(load_spec(spec), tmp_path / "r2")
    assert len({r.env_id for r in runs}) >= (1 if name == "suite-report-lava" else 4)
    assert all(r.status == "new" for r in runs)
    if name == "suite-tune":  # every illm setting is a row of its own, the controls at the small weights
        labels = {r.label for r in runs}
        assert {"illm-setting=paper", "illm-setting=small", "illm-setting=paper-literal", "illm-setting=small-gated",
                "illm-setting=capped", "illm-setting=bulk-small", "ppo", "rnd", "illm-shuffled",
                "illm-noreward"} == labels
        literal = next(r.config for r in runs if r.label == "illm-setting=paper-literal")
        assert literal.bonus.reward_streams == 1 and literal.bonus.action_target == "argmax"
        bulk = next(r.config for r in runs if r.label == "illm-setting=bulk-small")
        assert bulk.targets.live_budget == 0 and bulk.targets.cache.name == "ann-bulk"
        assert {r.config.total_steps for r in runs} == {61440, 81920, 122880, 151552}
    if name == "suite-report":  # the claim: both halves, 5 seeds, the report half's eighth level by suite-tune's rule
        frames = {r.env_id: r.config.total_steps for r in runs}
        assert len(runs) == 200 and frames["MiniGrid-LavaCrossingS9N1-v0"] == 368640
        assert frames["MiniGrid-Unlock-v0"] == 81920 and "BabyAI-KeyCorridorS3R2-v0" not in frames
    if name == "suite-report-lava":  # the suite's eighth level by its rule, at its calibrated budget
        assert {r.config.total_steps for r in runs} == {368640} and len(runs) == 25


def test_only_trains_the_runs_its_patterns_pick_and_leaves_the_rest(tmp_path):
    """--only picks runs by label or by path (shell wildcards): only they are trained, a later call
    without it finds them finished; a pattern that picks nothing is refused in one line."""
    spec, results = write(tmp_path, TINY), tmp_path / "results"
    out = runner.invoke(app, ["experiment", str(spec), "--out", str(results), "--dry-run", "--only", "*=2"])
    assert out.exit_code == 0 and "--only picks 2 of them" in out.output, out.output
    assert [line.split()[-1].split("/results/")[-1] for line in out.output.splitlines()[1:]] == [
        "BabyAI-GoToLocal-v0/ppo-num_dists=2/seed0", "BabyAI-GoToLocal-v0/ppo-num_dists=2/seed1"]
    out = runner.invoke(app, ["experiment", str(spec), "--out", str(results), "--only", "*/ppo-num_dists=1/seed1"])
    assert out.exit_code == 0 and "all 1 run finished (3 runs of the grid not picked by --only)" in out.output, \
        out.output
    assert [r.status for r in plan(load_spec(spec), results)] == ["new", "done", "new", "new"]
    refused = runner.invoke(app, ["experiment", str(spec), "--out", str(results), "--only", "rnd"])
    assert refused.exit_code == 1 and len(refused.output.strip().splitlines()) == 1, refused.output
    assert "--only 'rnd' matches no run of this spec; its labels: ppo-num_dists=1, ppo-num_dists=2" in refused.output


@pytest.mark.slow
def test_ctrl_c_stops_a_local_grid_with_a_checkpoint_per_run_and_the_same_command_resumes(tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while two runs train at
    --jobs 2: one line says what it finishes, each run ends its update and writes a checkpoint, the
    command exits 130 with no traceback from any worker, and the runs plan as "resume"."""
    import os
    import signal
    import subprocess
    import sys
    import time

    spec = write(tmp_path, TINY.replace("frames: 64", "frames: 200000").replace("  num_dists: [1, 2]",
                                                                                "  num_dists: [1]"))
    results = tmp_path / "results"
    proc = subprocess.Popen([sys.executable, "-m", "cli.main", "experiment", str(spec), "--out", str(results),
                             "--jobs", "2"], env={**os.environ, "HF_HUB_OFFLINE": "1"}, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    logs = [results / "BabyAI-GoToLocal-v0" / "ppo-num_dists=1" / f"seed{s}" / "metrics.jsonl" for s in (0, 1)]
    deadline = time.monotonic() + 120
    while not all(p.exists() and p.read_text().count("\n") >= 2 for p in logs):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"the grid ended or never trained: {proc.communicate()}")
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in out + err and "KeyboardInterrupt" not in err, err
    assert "SIGINT: finishing the runs' current updates, then a checkpoint each" in err, err
    assert err.count("stopped at ") == 2 and "stopped: 2 runs not finished (2 with a checkpoint)" in err, err
    assert all((p.parent / "checkpoint.pt").exists() for p in logs)
    assert [r.status for r in plan(load_spec(spec), results)] == ["resume", "resume"]


def test_a_runs_outcome_says_whether_a_stop_left_a_checkpoint():
    """A run stopped after an update has a checkpoint (status "stopped"); one stopped before its first
    update has none and plans as new; a failure is one line; a finished run is done."""
    from concurrent.futures import Future

    from illm_tools.experiment import Run
    from illm_tools.experiment.launch import _outcome

    def outcome(result=None, error=None):
        future, run = Future(), Run("BabyAI-GoToLocal-v0", "ppo", 0, None)
        future.set_exception(error) if error is not None else future.set_result(result)
        return _outcome(run, future), run.status

    assert outcome({"global_step": 4096}) == ("done", "done")
    assert outcome({"stopped": True, "global_step": 4096}) == ("stopped at 4,096 frames (checkpoint written)", "stopped")
    assert outcome({"stopped": True, "global_step": 0}) == ("stopped before its first update", "new")
    event, status = outcome(error=UsageError("--num-envs must be positive"))
    assert status == "failed" and event.startswith("failed") and "--num-envs must be positive" in event
