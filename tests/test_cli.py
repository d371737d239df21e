"""The command line: --help for every command, the collect -> data info path, and one-line errors
with non-zero exit codes that leave what is on disk untouched."""

from __future__ import annotations

import json

import datasets
import pytest
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()


def commands(group=app, prefix=()):
    import typer.main

    click_group = typer.main.get_command(group)
    out = []

    def walk(cmd, path):
        out.append(path)
        for name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, path + (name,))

    walk(click_group, prefix)
    return out


@pytest.mark.parametrize("path", commands(), ids=lambda p: " ".join(p) or "illm")
def test_every_command_has_help_with_an_example(path):
    result = runner.invoke(app, [*path, "--help"])
    assert result.exit_code == 0, result.output
    if path and path[-1] not in ("data", "cache"):
        assert "Example: illm" in result.output


def test_version():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.startswith("illm ")


def test_collect_then_info(tmp_path):
    out = tmp_path / "traj"
    result = runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", "300", "--num-envs", "4",
                                 "--out", str(out), "--seed", "3"])
    assert result.exit_code == 0, result.output
    assert "collected 300 steps" in result.output
    ds = datasets.load_from_disk(str(out))
    assert len(ds) == 300 and ds[0]["renderer"] == "babyai-text@1"
    assert ds[0]["obs_text"].startswith("You see") or ds[0]["obs_text"].startswith("You carry")
    info = runner.invoke(app, ["data", "info", str(out), "--json"])
    stats = json.loads(info.output)
    assert stats["rows"] == 300 and stats["env_ids"] == ["BabyAI-GoToLocal-v0"] and stats["schema_version"] == 1


def test_a_short_random_collection_says_its_episodes_still_running_and_warns_its_score_leans_quick(tmp_path):
    """300 random steps on GoToLocal over 8 envs: no episode has reached its time limit yet, so only the
    quick successes finished; the closing line counts the running ones and a warning says the rate is
    biased. 3,000 steps: most episodes finished, no warning."""
    from illm_tools.collect import CollectConfig, collect

    short = runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", "300", "--num-envs", "8",
                                "--out", str(tmp_path / "short"), "--seed", "0"])
    assert short.exit_code == 0, short.output
    assert "and 8 still running at the end" in short.output
    assert "warning: only" in short.output and "leans toward them" in short.output
    long = collect(CollectConfig(env_id="BabyAI-GoToLocal-v0", out=tmp_path / "long", steps=3000, num_envs=8, seed=0))
    assert long["episodes_running"] == 8 and long["episodes_finished"] > 16 and not long["biased"]


def test_collect_refuses_existing_output_and_keeps_it(tmp_path):
    out = tmp_path / "traj"
    args = ["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", "40", "--num-envs", "2", "--out", str(out)]
    assert runner.invoke(app, args).exit_code == 0
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    result = runner.invoke(app, args)
    assert result.exit_code == 1
    assert "already holds data: pass --append" in result.output
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    again = runner.invoke(app, [*args, "--append"])  # the same seeds would log the same episodes again
    assert again.exit_code == 1 and "already holds BabyAI-GoToLocal-v0 episodes with seeds 0–" in again.output
    hint = again.output.split("pass --seed ")[1].split()[0]
    assert runner.invoke(app, [*args, "--append", "--seed", hint]).exit_code == 0
    stats = json.loads(runner.invoke(app, ["data", "info", str(out), "--json"]).output)
    assert stats["rows"] == 80 and stats["finished_episodes"] <= stats["episodes"]
    assert [(p["seed"], p["action_space"], p["rows"]) for p in stats["parts"]] == [(0, "original", 40),
                                                                                   (int(hint), "original", 40)]
    assert "(3), episode seeds from 0" in runner.invoke(app, ["data", "info", str(out)]).output
    other = runner.invoke(app, [*args[:2], "BabyAI-GoToObj-v0", *args[3:], "--append", "--seed", "1000"])
    assert other.exit_code == 1 and "--mix-envs" in other.output
    assert runner.invoke(app, [*args[:2], "BabyAI-GoToObj-v0", *args[3:], "--append", "--seed", "1000",
                               "--mix-envs"]).exit_code == 0
    assert runner.invoke(app, [*args, "--append", "--overwrite"]).exit_code != 0


def test_unknown_env_is_one_line_with_close_matches(tmp_path):
    result = runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocl-v0", "--steps", "10", "--out", str(tmp_path / "x")])
    assert result.exit_code == 1
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "did you mean BabyAI-GoToLocal-v0" in lines[0]
    assert not (tmp_path / "x").exists()


def test_data_info_on_a_missing_folder(tmp_path):
    result = runner.invoke(app, ["data", "info", str(tmp_path / "none")])
    assert result.exit_code == 1 and "illm collect" in result.output


def test_boolean_flags_show_as_flags_in_help():
    for command in (["collect"], ["annotate"], ["train"], ["cache", "repair"], ["data", "coverage"]):
        out = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "160"})
        assert out.exit_code == 0 and "<bool>" not in out.output and "--help" in out.output, command


def test_no_stage_writes_into_a_folder_another_stage_owns(tmp_path):
    traj, cache, run = tmp_path / "traj", tmp_path / "ann", tmp_path / "run"
    assert runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", "32", "--num-envs", "2",
                               "--out", str(traj)]).exit_code == 0
    assert runner.invoke(app, ["train", "--method", "ppo", "--frames", "64", "--num-envs", "2", "--num-steps", "32",
                               "--out", str(run)]).exit_code == 0
    cache.mkdir()
    (cache / "manifest.json").write_text(json.dumps({"format": "illm.annotation-cache", "kind": "annotation",
                                                     "version": 1, "shards": []}))
    before = {p: sorted(q.name for q in p.iterdir()) for p in (traj, cache, run)}
    for folder, kind in ((traj, "trajectory dataset"), (cache, "annotation cache")):
        out = runner.invoke(app, ["train", "--method", "ppo", "--frames", "64", "--out", str(folder)])
        assert out.exit_code == 1 and (f"holds an {kind}" in out.output or f"holds a {kind}" in out.output), out.output
    out = runner.invoke(app, ["annotate", str(traj), "--cache", str(run)])
    assert out.exit_code == 1 and "holds a training run" in out.output
    for folder in (cache, run):
        out = runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", "8", "--out", str(folder),
                                  "--overwrite"])
        assert out.exit_code == 1
    assert before == {p: sorted(q.name for q in p.iterdir()) for p in (traj, cache, run)}


def test_without_a_terminal_progress_is_plain_periodic_lines(tmp_path, monkeypatch):
    import cli.common

    monkeypatch.setattr(cli.common, "PLAIN_EVERY_S", 0.0)
    out = runner.invoke(app, ["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", "64", "--num-envs", "2",
                              "--out", str(tmp_path / "t")])
    assert out.exit_code == 0, out.output
    lines = [line for line in out.output.splitlines() if line.startswith("collect BabyAI-GoToLocal-v0: ")]
    assert lines and "/64 steps" in lines[-1] and "left" in lines[-1] and "\x1b[" not in out.output


def test_illm_warnings_are_plain_lines(tmp_path):
    import logging

    runner.invoke(app, ["data", "info", str(tmp_path / "none")])  # sets up illm's logging
    handler = next(h for h in logging.getLogger("illm_tools").handlers if type(h.formatter).__name__ == "_IllmFormat")
    record = logging.LogRecord("illm_tools.rl.live", logging.WARNING, __file__, 1, "worker stopped", None, None)
    assert handler.format(record) == "warning: worker stopped"


def test_the_docs_model_table_and_illm_models_list_the_same_aliases():
    import re
    from pathlib import Path

    from illm_tools.llm.registry import list_models

    page = (Path(__file__).resolve().parents[1] / "docs" / "concepts" / "models.md").read_text()
    table = page[page.index("| alias | model | notes |"):].split("\n\n")[0]
    in_docs = {a for line in table.splitlines()[2:] for a in re.findall(r"`([a-z0-9.\-]+)`", line.split("|")[1])}
    assert in_docs == {m.alias for m in list_models()}


def test_frames_rounded_to_whole_rollouts_is_said(tmp_path, monkeypatch):
    import illm_tools.rl.run as run_module

    monkeypatch.setattr(run_module, "train", lambda cfg, on_metrics=None, should_stop=None, started=None: {"global_step": 0})
    out = runner.invoke(app, ["train", "--method", "ppo", "--frames", "1000", "--out", str(tmp_path / "r")])
    assert "--frames 1,000 is not a whole number of rollouts" in out.output and "the run trains 2,048 frames" in out.output


def test_every_train_setting_is_an_option_named_as_its_field_with_its_default(tmp_path, monkeypatch):
    import typer.main

    import illm_tools.rl.run as run_module
    from illm_tools.rl.build import run_config
    from illm_tools.rl.config import FLAT

    command = typer.main.get_command(app).commands["train"]
    opts = {o for p in command.params for o in p.opts}
    fields = list(FLAT)  # every setting by its flat name (the LLM's and iLLM's too)
    dict_fields = {"bonus_options", "network_options", "env_options", "task_weights"}
    renamed = {"mode": "--method", "obs_mode": "--mode"}  # the method's field is "mode"; --mode is obs|hop
    assert all(renamed.get(f, "--" + f.replace("_", "-")) in opts for f in fields if f not in dict_fields)
    wrong = runner.invoke(app, ["train", "--out", str(tmp_path / "w"), "--mode", "illm"])
    assert wrong.exit_code == 1 and "the method is --method" in wrong.output
    assert {"--frames", "--out", "--method", "--env", "--history", "--dtype", "--bonus-option"} <= opts
    seen = []
    monkeypatch.setattr(run_module, "train", lambda cfg, on_metrics=None, should_stop=None, started=None: seen.append(cfg) or {})
    out = runner.invoke(app, ["train", "--out", str(tmp_path / "r"), "--method", "ppo", "--no-anneal-lr",
                              "--clip-coef", "0.1", "--env-option", "num_dists=4", "--target-kl", "0.02"])
    assert out.exit_code == 0, out.output
    (cfg,) = seen
    default = run_config({"run_dir": tmp_path / "r", "method": "ppo"})  # the Python API's path: the same builder
    changed = {k for k, v in cfg.flat().items() if v != default.flat()[k]}
    assert changed == {"anneal_lr", "clip_coef", "env_options", "target_kl"}  # every other default is the field's
    assert cfg.env_options == {"num_dists": 4} and cfg.total_steps == 200_000


def test_probe_refuses_an_out_it_would_overwrite_or_cannot_write_before_probing(tmp_path, monkeypatch):
    """`illm probe --out`: an existing file, a folder, or a path under a file is refused in one line
    before the probe runs; the existing file is left as it was."""
    import illm_tools.probe

    monkeypatch.setattr(illm_tools.probe, "probe", lambda *a, **k: (_ for _ in ()).throw(AssertionError("ran")))
    kept = tmp_path / "kept.json"
    kept.write_text("{}")
    for out, said in ((kept, "would be overwritten"), (tmp_path, "is a folder"), (kept / "x.json", "a file")):
        result = runner.invoke(app, ["probe", "--backend", "oracle", "--states", "4", "--out", str(out)])
        assert result.exit_code == 1 and said in result.output and len(result.output.strip().splitlines()) == 1
    assert kept.read_text() == "{}"


def test_every_commands_summary_is_one_unbroken_sentence():
    """`illm --help`'s rows: a docstring's hard line breaks no longer reach Rich's layout (issue 31), and
    each command's row is its first sentence."""
    from cli.main import app

    def commands(typer_app):
        for info in typer_app.registered_commands:
            yield info
        for group in typer_app.registered_groups:
            yield from commands(group.typer_instance)

    infos = list(commands(app))
    assert len(infos) >= 12
    for info in infos:
        assert info.short_help and "\n" not in info.short_help, info.name
        assert ". " not in info.short_help.rstrip("."), info.short_help
        assert all("\n" not in p for p in info.help.split("\n\n")), info.name


@pytest.mark.parametrize("group", [(), ("data",), ("cache",)], ids=lambda g: " ".join(("illm", *g)))
def test_each_commands_row_in_help_is_one_line_at_100_columns(group):
    """`illm --help` is a first screen (issue 31): at 100 columns every command's summary fits its row,
    so no row of the Commands panel runs onto a second line."""
    result = runner.invoke(app, [*group, "--help"], env={"COLUMNS": "100"})
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert max(len(line) for line in lines) <= 100
    start = next(i for i, line in enumerate(lines) if "─ Commands ─" in line)
    rows = []
    for line in lines[start + 1:]:
        if line.startswith("╰"):
            break
        rows.append(line.strip("│ \n"))
        assert not line.startswith("│  "), f"a summary runs onto a second line: {line!r}"
    assert {row.split()[0] for row in rows} == {p[-1] for p in commands() if p[:-1] == group and p}
