"""ChibiT-style policy: torso initialised from the embedded LLM's blocks, fine-tuned, no bonus."""

from __future__ import annotations

import pytest
import torch
from typer.testing import CliRunner

from cli.main import app
from illm_tools.errors import UsageError
from illm_tools.rl.config import TrainConfig

runner = CliRunner()


def test_network_options_are_checked_before_anything_loads(tmp_path):
    with pytest.raises(UsageError, match="blocks must be at least 1"):
        TrainConfig(method="chibit", run_dir=tmp_path, network_options={"blocks": "0"})
    with pytest.raises(UsageError, match="has no network option depth; it takes blocks, model"):
        TrainConfig(method="chibit", run_dir=tmp_path, network_options={"depth": "2"})
    with pytest.raises(UsageError, match="--method ppo takes no network option"):
        TrainConfig(method="ppo", run_dir=tmp_path, network_options={"blocks": "2"})
    out = runner.invoke(app, ["train", "--method", "chibit", "--network-option", "blocks", "--out", str(tmp_path / "r")])
    assert out.exit_code == 1 and "--network-option takes KEY=VALUE" in out.output


@pytest.mark.slow
def test_chibit_torso_starts_from_the_llm_blocks_and_is_fine_tuned(tmp_path, smollm2_cache_env):
    from illm_tools.llm.loading import load_model
    from illm_tools.rl.checkpoint import load_checkpoint

    lm = load_model("smollm2-135m", dtype="float32")
    first = lm.model.model.layers[0].mlp.down_proj.weight
    run = tmp_path / "run"
    out = runner.invoke(app, ["train", "--method", "chibit", "--frames", "256", "--num-envs", "4", "--num-steps", "32",
                              "--network-option", "blocks=1", "--out", str(run)])
    assert out.exit_code == 0, out.output
    state = load_checkpoint(run)["model"]
    assert not any(k.startswith("f_a.") or k.startswith("blocks.1.") for k in state)  # no heads, one block
    trained = state["blocks.0.mlp.down_proj.weight"]
    assert trained.shape == first.shape and not torch.equal(trained, first)  # fine-tuned
    assert torch.allclose(trained, first, atol=0.05)  # from the LLM's weights, not a fresh init
    (row,) = __import__("json").loads(runner.invoke(app, ["eval", str(run), "--episodes", "2", "--json"]).output)
    assert row["method"] == "chibit" and row["frames"] == 256
