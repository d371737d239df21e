"""Issue 69, findings 4, 5 and 12: secrets never reach a file, and every path a file names is a bare
name inside its folder. A token given to `illm train` appears in no file of the run or its report
(`illm_tools.provenance.redact`); `illm report --merge` copies no heatmap from or to outside the
folders and refuses a malformed part in one line (`illm_tools.report.results`); an experiment spec's
name, a bundle's name and a plain grid value never become a path outside the results folder."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from fakes import fake_run
from illm_tools import provenance
from illm_tools.errors import UsageError

TOKEN = "Zq7-trust-files-token-4b1c9e"  # a token's shape (`annotate.wire.check_token`)
SMALL = ["--method", "ppo", "--num-envs", "2", "--num-steps", "32", "--seed", "0"]  # 64 frames per update
ENV, OTHER = "BabyAI-GoToLocal-v0", "BabyAI-UnlockLocal-v0"


def illm(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_line_refusal(result, *expected: str) -> None:
    assert result.exit_code == 1, result.output
    assert len(result.output.strip().splitlines()) == 1 and "Traceback" not in result.output, result.output
    for text in expected:
        assert text in result.output, result.output


def files_holding(folder: Path, text: str) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file() and text.encode() in p.read_bytes())


# --- finding 4: a token reaches no file ----------------------------------------------------------------

def test_a_token_on_the_command_line_reaches_no_file_of_the_run_or_its_report(tmp_path, monkeypatch):
    """`illm train --annotator-token T` (then `--annotator-token=T` on resume), `illm report` and a merge
    of reports: T is in no file written; the commands are still recorded, T as REDACTED."""
    from illm_tools.annotate.wire import TOKEN_ENV

    monkeypatch.setenv(TOKEN_ENV, "")  # `use_token` sets it for the run; put back after the test
    run, report, joined = tmp_path / "run", tmp_path / "report", tmp_path / "joined"
    unreachable = "http://127.0.0.1:9"  # ppo reads no targets: the annotator is never asked
    argv = ["illm", "train", *SMALL, "--frames", "64", "--out", str(run), "--annotator", unreachable,
            "--annotator-token", TOKEN]
    monkeypatch.setattr(sys, "argv", argv)
    assert illm(*argv[1:]).exit_code == 0
    argv = ["illm", "train", "--out", str(run), "--resume", "--frames", "128", "--annotator", unreachable,
            f"--annotator-token={TOKEN}"]
    monkeypatch.setattr(sys, "argv", argv)
    assert illm(*argv[1:]).exit_code == 0
    entries = json.loads((run / "provenance.json").read_text())
    assert [e["command"].split("--annotator-token")[1][:9] for e in entries] == [" REDACTED", "=REDACTED"]
    assert {p.name for p in run.iterdir()} >= {"config.json", "checkpoint.pt", "metrics.jsonl", "provenance.json"}
    assert files_holding(run, TOKEN) == []

    old = [{**entries[0], "command": f"illm train --annotator-token {TOKEN} --out {run}"}]  # as c7a39f0 wrote it
    (run / "provenance.json").write_text(json.dumps(old))
    monkeypatch.setattr(sys, "argv", ["illm", "report", str(run), "--out", str(report)])
    assert illm("report", run, "--every", 64, "--bootstrap", 20, "--out", report).exit_code == 0
    (row,) = json.loads((report / "results.json").read_text())["rows"]
    assert row["provenance"][str(run)][0]["command"] == f"illm train --annotator-token REDACTED --out {run}"

    part = tmp_path / "part"  # a part written before redaction: its own command and its runs' hold the token
    shutil.copytree(report, part)
    results = json.loads((part / "results.json").read_text())
    results["settings"]["command"] = f"illm report --annotator-token={TOKEN}"
    results["rows"][0]["provenance"] = {str(run): old}
    (part / "results.json").write_text(json.dumps(results))
    other = tmp_path / "other"
    shutil.copytree(report, other)
    renamed = json.loads((other / "results.json").read_text())
    renamed["envs"], renamed["rows"][0]["env_id"] = [OTHER], OTHER
    (other / "results.json").write_text(json.dumps(renamed))
    assert illm("report", part, other, "--merge", "--out", joined).exit_code == 0

    assert files_holding(report, TOKEN) == [] and files_holding(joined, TOKEN) == []
    assert json.loads((joined / "results.json").read_text())["settings"]["parts"][0]["command"] == \
        "illm report --annotator-token=REDACTED"


def test_every_option_that_names_a_secret_is_redacted_and_only_those():
    """Each option of the command line whose name speaks of a token, key or password: a secret by
    `provenance.secret_option` (its value never written), or one of these, which carry none."""
    import typer

    not_secrets = {"--api-key-env": "the name of a variable, not its value", "--batch-tokens": "a count",
                   "--max-tokens": "a count"}
    found = {}

    def walk(command, path):
        if hasattr(command, "list_commands"):
            for name in command.list_commands(None):
                walk(command.get_command(None, name), [*path, name])
            return
        for param in command.params:
            for flag in [*param.opts, *param.secondary_opts]:
                if any(word in flag.lower() for word in ("token", "key", "secret", "pass", "cred", "auth")):
                    found[flag] = provenance.secret_option(flag)

    walk(typer.main.get_command(app), [])
    assert {flag for flag, secret in found.items() if secret} == {"--token", "--annotator-token"}
    assert {flag for flag, secret in found.items() if not secret} <= set(not_secrets)


@pytest.mark.parametrize("argv,expected", [
    (["illm", "serve", "--token", "s3cret", "--port", "1"], ["illm", "serve", "--token", "REDACTED", "--port", "1"]),
    (["illm", "x", "--api-key=abc", "--api-key-env", "OPENAI_KEY"], ["illm", "x", "--api-key=REDACTED", "--api-key-env",
                                                                       "OPENAI_KEY"]),
    (["illm", "train", "--annotator", "http://me:pw@host:8/v1"], ["illm", "train", "--annotator", "http://me:REDACTED@host:8/v1"]),
    (["illm", "train", "--annotator-token"], ["illm", "train", "--annotator-token"]),  # no value given: nothing to hide
    (["illm", "train", "--annotator", "http://me:p@ss@host:8/v1"], ["illm", "train", "--annotator",
                                                                   "http://me:REDACTED@host:8/v1"]),  # @ in the password
    (["illm", "train", "--annotator", "http://me:a/b@host:8/v1"], ["illm", "train", "--annotator",
                                                                  "http://me:REDACTED@host:8/v1"]),  # / in the password
    (["illm", "train", "--annotator", "http://host:8/v1?x=a@b"], ["illm", "train", "--annotator",
                                                                 "http://host:8/v1?x=a@b"]),  # a query is no password
])
def test_redaction_hides_both_forms_of_a_secret_option_and_a_urls_password(argv, expected):
    assert provenance.redact_argv(argv) == expected
    assert "s3cret" not in provenance.redact("illm serve --token 's3cret'")
    assert provenance.redact('illm train --token "unclosed').startswith("(withheld")


# --- finding 5: a merged part names files inside its folder, and a malformed one is one line ------------

@pytest.fixture(scope="module")
def part(tmp_path_factory) -> Path:
    """A report folder of one env (two methods, two seeds) with a visitation heatmap; its runs are gone."""
    from illm_tools.report.build import build_report

    root = tmp_path_factory.mktemp("part")
    runs = []
    for seed in range(2):
        for mode, final in (("ppo", 0.2), ("illm", 0.6)):
            runs.append(root / f"{mode}-{seed}")
            fake_run(runs[-1], seed, [(100, final / 2, 1), (200, final, 1)], mode=mode)
            np.save(runs[-1] / "visitation.npy", np.ones((8, 8)))
    build_report(runs, root / "report", every=100, reps=20)
    return root / "report"


def parts(tmp_path: Path, part: Path, edit=None) -> tuple[Path, Path]:
    """Two parts (the fixture's, and a copy for another env) under tmp_path/a/b/; `edit` changes the
    second's results.json."""
    first, second = tmp_path / "a" / "b" / "part0", tmp_path / "a" / "b" / "part1"
    shutil.copytree(part, first)
    shutil.copytree(part, second)
    results = json.loads((second / "results.json").read_text())
    results["envs"] = [OTHER]
    for row in results["rows"]:
        row["env_id"] = OTHER
    if edit is not None:
        edit(results)
    (second / "results.json").write_text(json.dumps(results))
    return first, second


@pytest.mark.parametrize("png", ["../../planted.txt", "ABSOLUTE", "sub/x.png", ".."])
def test_a_merged_part_cannot_name_a_file_outside_its_folder(tmp_path, part, png):
    """A heatmap named `../../planted.txt` (or absolute, or in a subfolder) would be read from outside
    the part and written outside --out: refused in one line naming the file, and nothing written."""
    out = tmp_path / "x" / "y" / "joined"
    planted, victim = tmp_path / "a" / "planted.txt", tmp_path / "x" / "planted.txt"
    planted.parent.mkdir(parents=True)
    planted.write_text("from the part")
    victim.parent.mkdir(parents=True)
    victim.write_text("the user's own")
    name = str(victim) if png == "ABSOLUTE" else png

    def plant(results):
        results["rows"][0]["visitation"]["png"] = name

    first, second = parts(tmp_path, part, plant)
    one_line_refusal(illm("report", first, second, "--merge", "--out", out),
                     str(second / "results.json"), "rows[0].visitation.png", "not a bare name")
    assert victim.read_text() == "the user's own" and not out.exists()
    one_line_refusal(illm("report", second, "--redraw"), "rows[0].visitation.png")


def test_a_merge_copies_each_parts_heatmaps_beside_its_rows(tmp_path, part):
    """The merge the refusals above protect still works: the parts' heatmaps are copied into --out."""
    first, second = parts(tmp_path, part)
    out = tmp_path / "joined"
    result = illm("report", first, second, "--merge", "--out", out)
    assert result.exit_code == 0, result.output
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert len(rows) == 4 and all(r["visitation"] and (out / r["visitation"]["png"]).is_file() for r in rows)


def _drop(*path):
    def edit(results):
        *head, last = path
        node = results
        for key in head:
            node = node[key]
        del node[last]
    return edit


def _set(value, *path):
    def edit(results):
        *head, last = path
        node = results
        for key in head:
            node = node[key]
        node[last] = value
    return edit


def test_a_part_nested_too_deep_to_read_is_refused_in_one_line(tmp_path, part):
    first, second = parts(tmp_path, part)
    (second / "results.json").write_text("[" * 100_000 + "]" * 100_000)
    for args in ((first, second, "--merge", "--out", tmp_path / "joined"), (second, "--redraw")):
        one_line_refusal(illm("report", *args), str(second / "results.json"), "RecursionError")
    assert not (tmp_path / "joined").exists()


@pytest.mark.parametrize("edit,field", [
    (_drop("rows", 0, "score_name"), "rows[0] has no 'score_name'"),  # the finding's KeyError
    (_drop("rows", 1, "final", "iqm"), "rows[1].final has no 'iqm'"),
    (_set("high", "rows", 0, "final", "iqm"), "rows[0].final.iqm must be a number or null"),
    (_set([0.1], "rows", 0, "mean"), "rows[0].mean has 1 values for 2 frames"),
    (_set("many", "settings", "bootstrap_reps"), "settings.bootstrap_reps must be a whole number"),
    (_set({"x": 1}, "rows"), "the file.rows must be a list"),
    (_set(7, "rows", 0), "rows[0] must be a mapping"),
    (_set({"png": 3, "runs": []}, "rows", 0, "visitation"), "rows[0].visitation.png must be a file name"),
    (_set(["x"], "rows", 0, "runs"), "rows[0].trained_frames misses one of its runs"),
])
def test_a_malformed_part_is_refused_in_one_line_naming_it(tmp_path, part, edit, field):
    first, second = parts(tmp_path, part, edit)
    out = tmp_path / "joined"
    one_line_refusal(illm("report", first, second, "--merge", "--out", out), str(second / "results.json"), field)
    assert not out.exists()


def test_the_shipped_reports_pass_the_check():
    """Every report folder under docs/results (written by older versions too) reads back as it is."""
    from illm_tools.report.results import read_results

    shipped = Path(__file__).resolve().parents[1] / "docs" / "results"
    folders = sorted(p.parent for p in shipped.glob("*/results.json"))
    if not folders:
        pytest.skip(f"no report folders under {shipped} in this checkout")
    for folder in folders:
        read_results(folder, "")


# --- finding 12: a spec's names are bare names --------------------------------------------------------

SPEC = """\
name: {name}
frames: 64
seeds: 1
envs: [BabyAI-GoToLocal-v0]
methods: [ppo]
grid:
  {key}: [{value}]
settings:
  num_envs: 2
  num_steps: 32
"""


@pytest.mark.parametrize("name,key,value,expected", [
    ("../outside", "ent_coef", "0.1", "line 1: name: '../outside' is not a bare name"),
    ("/tmp/elsewhere", "ent_coef", "0.1", "line 1: name: '/tmp/elsewhere' is not a bare name"),
    ("ok", "ent_coef", "{name: ../../../../x, ent_coef: 0.1}", "line 7: the bundle name: '../../../../x' is not a bare name"),
    ("ok", "cache", "../../../../x", "line 7: the grid value of cache: 'cache=../../../../x' is not a bare name"),
])
def test_a_spec_names_no_folder_outside_its_results(tmp_path, monkeypatch, name, key, value, expected):
    """`illm experiment SPEC --dry-run` with a spec named `../outside` planned results/../outside/...;
    a bundle's name and a plain grid value become a run's folder the same way. Each is refused."""
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC.format(name=name, key=key, value=value))
    one_line_refusal(illm("experiment", spec, "--dry-run"), expected)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]


def test_a_plainly_named_spec_still_plans(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC.format(name="fine", key="ent_coef", value="{name: low, ent_coef: 0.1}"))
    result = illm("experiment", spec, "--dry-run")
    assert result.exit_code == 0, result.output
    assert str(Path("results") / "fine" / ENV / "ppo-ent_coef=low" / "seed0") in result.output


@pytest.mark.parametrize("name", ["", ".", "..", "a/b", "a\\b", "/abs", "x\x00y", "é" * 128, 7])
def test_bare_name_refuses_every_name_that_is_not_one(name):
    from illm_tools.folders import bare_name

    with pytest.raises(UsageError, match="is not a bare name"):
        bare_name(name, "here", "fix it")
    assert bare_name("visitation-BabyAI-GoToLocal-v0-illm.png", "here", "") == "visitation-BabyAI-GoToLocal-v0-illm.png"
