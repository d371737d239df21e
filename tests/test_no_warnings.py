"""Nothing of a third party spills into illm's output: a short collect, annotate (ranking and
generation) and train with live annotation run with every Python warning turned into an error
(this test overrides the suite's ignore filters) and no library logger speaking at warning level.
A transformers API marked for removal (past_key_values passed as a tuple, `torch_dtype`, ...) or a
gymnasium / datasets deprecation reached from illm's calls fails here before a user sees it."""

from __future__ import annotations

import logging
import warnings

import pytest
from typer.testing import CliRunner

from cli.main import app

runner = CliRunner()
pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")
OWN = ("illm_tools", "cli", "illm")
LIBRARIES = ("transformers", "datasets", "accelerate", "peft", "torch", "gymnasium", "huggingface_hub")
"""Their loggers, some of which (transformers, datasets) keep their own handler and do not propagate:
the test listens to each directly."""


@pytest.mark.slow  # 12 s: three stages end to end
@pytest.mark.filterwarnings("error")
def test_annotate_and_train_raise_no_third_party_warning(tmp_path, tiny_lm, caplog):
    model, traj, ann = tiny_lm.spec.path, tmp_path / "traj", tmp_path / "ann"
    steps = [["collect", "--env", "BabyAI-GoToLocal-v0", "--steps", 32, "--num-envs", 2, "--out", traj],
             ["annotate", traj, "--cache", ann, "--model", model, "--dtype", "float32", "--limit", 4,
              "--batch-size", 2, "--tasks", "action,summary", "--history", 0],
             ["train", "--env", "BabyAI-GoToLocal-v0", "--cache", ann, "--model", model, "--dtype", "float32",
              "--history", 0, "--num-envs", 2, "--num-steps", 16, "--frames", 64, "--live-budget", 2,
              "--live-mode", "sync", "--out", tmp_path / "run"]]
    loggers = [logging.getLogger(name) for name in LIBRARIES]
    for logger in loggers:
        logger.addHandler(caplog.handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with caplog.at_level(logging.WARNING):
                for args in steps:
                    out = runner.invoke(app, [str(a) for a in args])
                    assert out.exit_code == 0, (args[0], out.output, out.exception)
    finally:
        for logger in loggers:
            logger.removeHandler(caplog.handler)
    foreign = [f"{r.name}: {r.getMessage()}" for r in caplog.records
               if r.levelno >= logging.WARNING and not r.name.startswith(OWN)]
    assert not foreign, foreign
