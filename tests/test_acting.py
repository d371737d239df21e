"""`illm act`: an annotator acting greedily on its own ranking, beside a random policy."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from cli.main import app
from illm_tools.acting import wilson

runner = CliRunner()


def test_wilson_interval_is_sound_at_the_ends():
    assert wilson(0, 10)[0] == 0.0 and 0.2 < wilson(0, 10)[1] < 0.35
    assert wilson(10, 10)[1] == 1.0 and 0.65 < wilson(10, 10)[0] < 0.8
    low, high = wilson(50, 100)
    assert low < 0.5 < high and abs((0.5 - low) - (high - 0.5)) < 1e-9


def test_act_plays_the_oracle_beside_random_and_writes_its_figures(tmp_path):
    out = tmp_path / "act.json"
    said = runner.invoke(app, ["act", "--env", "BabyAI-GoToLocal-v0", "--backend", "oracle", "--episodes", "2",
                               "--out", str(out)])
    assert said.exit_code == 0, said.output
    assert "annotator" in said.output and "random" in said.output
    figures = json.loads(out.read_text())
    assert figures["config"]["episodes"] == 2 and set(figures["policies"]) == {"annotator", "random"}
    assert figures["policies"]["annotator"]["success_rate"] == 1.0
    again = runner.invoke(app, ["act", "--env", "BabyAI-GoToLocal-v0", "--backend", "oracle", "--episodes", "2",
                                "--out", str(out)])
    assert again.exit_code != 0 and "Traceback" not in again.output  # an existing file is not overwritten
    assert json.loads(out.read_text()) == figures


def test_bad_options_are_refused_in_one_line():
    for args, message in ((["--calibration", "max"], "--calibration must be one of"),
                          (["--episodes", "0"], "--episodes")):
        said = runner.invoke(app, ["act", "--env", "BabyAI-GoToLocal-v0", "--backend", "oracle", *args])
        assert said.exit_code != 0 and message in said.output and "Traceback" not in said.output, said.output
        assert len(said.output.strip().splitlines()) == 1
