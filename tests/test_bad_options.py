"""Every command refuses bad values of its numeric and path options in one line: a negative number,
NaN, a number past what it can hold, a file where a folder belongs, an input that is missing. The
refusal exits non-zero with no traceback, and nothing is written (the library call that would start
the work is replaced here by one that says it was reached: a bad value must never get that far).
The options are read from the commands themselves (click's parameters), so a new option is walked
as soon as it exists."""

from __future__ import annotations


import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from typer.main import get_command
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
REACHED = 97
"""Exit code of a replaced library call: the command accepted the values it was given."""

# command -> (the library functions that start its work, its other arguments: {inputs} filled in)
COMMANDS = {
    ("collect",): (["illm_tools.collect.collect"], ["--env", "BabyAI-GoToLocal-v0", "--out", "{tmp}/traj-new"]),
    ("annotate",): (["illm_tools.annotate.bulk.annotate_dataset"], ["{traj}", "--cache", "{tmp}/ann"]),
    ("train",): (["illm_tools.rl.run.train"], ["--method", "ppo", "--out", "{tmp}/run-new"]),
    ("eval",): (["illm_tools.rl.run.evaluate"], ["{run}"]),
    ("probe",): (["illm_tools.probe.probe"], []),
    ("serve",): (["illm_tools.serve.serve"], ["--cache", "{tmp}/ann"]),
    ("experiment",): (["illm_tools.experiment.run_experiment"], ["{spec}", "--out", "{tmp}/results"]),
    ("report",): (["illm_tools.report.build.build_report"], ["{run}", "--out", "{tmp}/report"]),
    ("data", "coverage"): (["illm_tools.annotate.coverage.measure_coverage"], ["{traj}"]),
    ("distil",): (["illm_tools.distil.run.distil"], ["{tmp}/ann", "--out", "{tmp}/student"]),
}
FOLDER_OPTIONS = {"--out", "--cache", "--run-dir", "--into"}
"""Options naming a folder a command writes (a file there must be refused)..."""
FILE_OPTIONS = {("probe", "--out")}
"""...but these, which name a file."""


def _command(path: tuple[str, ...]):
    command = get_command(app)
    for name in path:
        command = command.commands[name]  # type: ignore[attr-defined]
    return command


def _numeric(path: tuple[str, ...]) -> list[tuple[str, type]]:
    """(flag, int or float) of every numeric option of a command."""
    out = []
    for param in _command(path).params:  # by type name: Typer may carry its own copy of click
        if type(param).__name__ in ("Option", "TyperOption") and not getattr(param, "is_flag", False):
            kind = param.bare_type() if callable(getattr(param, "bare_type", None)) else type(param.type).__name__
            base = int if kind in ("int", "IntParamType", "IntRange") else \
                float if kind in ("float", "FloatParamType", "FloatRange") else None
            if base is not None:
                out.append((max(param.opts, key=len), base))
    return out


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A trajectory dataset, a finished run and a spec the commands may read."""
    tmp = tmp_path_factory.mktemp("inputs")
    for args in (["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", "64", "--num-envs", "2", "--out", str(tmp / "traj")],
                 ["train", "--method", "ppo", "--num-envs", "2", "--num-steps", "16", "--frames", "32",
                  "--out", str(tmp / "run")]):
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
    (tmp / "spec.yaml").write_text("name: s\nframes: 64\nseeds: 1\nenvs: [BabyAI-GoToLocal-v0]\nmethods: [ppo]\n"
                                   "settings: {num_envs: 2, num_steps: 16, num_minibatches: 2}\n")
    return {"traj": str(tmp / "traj"), "run": str(tmp / "run"), "spec": str(tmp / "spec.yaml")}


def _invoke(path, args, inputs, tmp_path, monkeypatch):
    """Run the command with the library replaced; (exit code, output, files written under tmp_path)."""
    import importlib

    def reached(*_a, **_k):
        raise SystemExit(REACHED)

    for target in COMMANDS[path][0]:
        module, _, name = target.rpartition(".")
        monkeypatch.setattr(importlib.import_module(module), name, reached)
    before = sorted(p for p in tmp_path.rglob("*"))
    filled = [a.format(tmp=tmp_path, **inputs) for a in COMMANDS[path][1]] + list(args)
    result = runner.invoke(app, [*path, *filled])
    written = sorted(set(tmp_path.rglob("*")) - set(before))
    return result.exit_code, result.output, written


def _refused(code: int, output: str, written: list) -> None:
    lines = [line for line in output.splitlines() if line.strip()]
    assert code not in (0, REACHED), f"accepted ({code}): {output}"
    assert "Traceback" not in output and len(lines) <= 2, output
    assert not written, written


CASES = [(path, flag, kind) for path in COMMANDS for flag, kind in _numeric(path)]


@pytest.mark.parametrize("path,flag,kind", CASES, ids=[f"{' '.join(p)} {f}" for p, f, _ in CASES])
def test_a_negative_or_nan_number_is_refused_in_one_line(path, flag, kind, inputs, tmp_path, monkeypatch):
    for bad in (["-1"] if kind is int else ["-1", "nan"]):
        _refused(*_invoke(path, [flag, bad], inputs, tmp_path, monkeypatch))


@pytest.mark.parametrize("path,flag,kind", [c for c in CASES if c[2] is int],
                         ids=[f"{' '.join(p)} {f}" for p, f, k in CASES if k is int])
@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(huge=st.integers(min_value=2**63, max_value=2**80))
def test_a_number_past_what_it_can_hold_is_refused(path, flag, kind, huge, inputs, tmp_path, monkeypatch):
    _refused(*_invoke(path, [flag, str(huge)], inputs, tmp_path, monkeypatch))  # the library never reached


@pytest.mark.parametrize("path", [p for p in COMMANDS if any(o in FOLDER_OPTIONS and (p[0], o) not in FILE_OPTIONS
                                                              for param in _command(p).params
                                                              for o in getattr(param, "opts", []))],
                         ids=lambda p: " ".join(p))
def test_a_file_where_a_folder_belongs_is_refused(path, inputs, tmp_path, monkeypatch):
    flags = [o for param in _command(path).params for o in getattr(param, "opts", [])
             if o in FOLDER_OPTIONS and (path[0], o) not in FILE_OPTIONS]
    for flag in flags:
        afile = tmp_path / "a-file"
        afile.write_text("not a folder")
        code, output, written = _invoke(path, [flag, str(afile)], inputs, tmp_path, monkeypatch)
        assert afile.read_text() == "not a folder"
        _refused(code, output, [w for w in written if w != afile])


@pytest.mark.parametrize("path", [p for p in COMMANDS if any("{traj}" in a or "{run}" in a or "{spec}" in a
                                                              for a in COMMANDS[p][1])], ids=lambda p: " ".join(p))
def test_a_missing_input_is_refused(path, tmp_path, monkeypatch):
    missing = {"traj": str(tmp_path / "no-traj"), "run": str(tmp_path / "no-run"), "spec": str(tmp_path / "no.yaml")}
    _refused(*_invoke(path, [], missing, tmp_path, monkeypatch))
