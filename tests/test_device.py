"""`--device`: names checked in one place, a GPU the machine lacks refused in one line before
anything is written, auto resolved and recorded; the `gpu`-marked tests run the CUDA paths where
there is a GPU and are skipped (conftest) where there is none."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from cli.main import app
from illm_tools.devices import check_device, resolve_device
from illm_tools.errors import UsageError

from fakes import FakePool, FakeProvider

runner = CliRunner()
ENV = "BabyAI-GoToLocal-v0"
NO_GPU = not torch.cuda.is_available()


def test_device_names_are_checked_and_auto_resolves():
    for good in ("cpu", "cuda", "cuda:0", "cuda:12", "auto"):
        check_device(good)
    for bad in ("gpu", "cuda:", "cuda:x", "CPU", "cuda:-1", ""):
        with pytest.raises(UsageError, match="must be cpu, cuda, cuda:N or auto"):
            check_device(bad)
    assert resolve_device("auto") == ("cpu" if NO_GPU else "cuda")
    assert resolve_device("cpu") == "cpu"


@pytest.mark.skipif(not NO_GPU, reason="this machine has a GPU")
@pytest.mark.parametrize("argv", [
    ["train", "--env", ENV, "--method", "ppo", "--device", "cuda"],
    ["train", "--env", ENV, "--method", "ppo", "--device", "cuda:1"],
    ["annotate", "DATA", "--cache", "CACHE", "--device", "cuda"],
])
def test_a_gpu_the_machine_lacks_is_one_line_and_nothing_is_written(tmp_path, argv):
    from illm_tools.collect import CollectConfig, collect

    if argv[0] == "annotate":
        collect(CollectConfig(env_id=ENV, out=tmp_path / "traj", steps=16, num_envs=2, seed=0))
        argv = [a.replace("DATA", str(tmp_path / "traj")).replace("CACHE", str(tmp_path / "ann")) for a in argv]
    else:
        argv = [*argv, "--out", str(tmp_path / "run"), "--frames", "64", "--num-envs", "2", "--num-steps", "32"]
    out = runner.invoke(app, argv)
    assert out.exit_code != 0 and "no CUDA device" in out.output, out.output
    assert len(out.output.strip().splitlines()) == 1 and "Traceback" not in out.output
    assert not (tmp_path / "run").exists() and not (tmp_path / "ann").exists()


def test_a_bad_device_name_is_refused_by_every_stage_in_one_line(tmp_path):
    for argv in (["train", "--env", ENV, "--device", "gpu", "--out", str(tmp_path / "run")],
                 ["train", "--env", ENV, "--llm-device", "tpu", "--out", str(tmp_path / "run")],
                 ["probe", "--env", ENV, "--device", "gpu"]):
        out = runner.invoke(app, argv)
        assert out.exit_code != 0 and "cpu, cuda, cuda:N or auto" in out.output, (argv, out.output)
        assert len(out.output.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_auto_is_recorded_resolved_and_a_run_may_resume_on_another_device(tmp_path):
    from illm_tools.rl import TrainConfig, Trainer

    cfg = TrainConfig(run_dir=tmp_path / "run", method="rnd", num_envs=4, num_steps=32, total_steps=128,
                      tensorboard=False, device="auto")
    trainer = Trainer(cfg.resolved(), FakePool(4))
    trainer.train()
    recorded = json.loads((tmp_path / "run" / "config.json").read_text())
    assert recorded["device"] == ("cpu" if NO_GPU else "cuda")
    assert trainer.net.critic_ext[0].weight.device.type == recorded["device"]
    resumed = Trainer(TrainConfig.from_dict(dict(**{**cfg.__dict__, "total_steps": 256, "resume": True, "device": "cpu"})).resolved(),
                      FakePool(4))
    assert resumed.global_step == 128 and resumed.train()["global_step"] == 256


def _short_run(tmp_path, name, method, device):
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.rl import TrainConfig, Trainer

    cfg = TrainConfig.from_dict(dict(run_dir=tmp_path / name, method=method, num_envs=4, num_steps=32, total_steps=256,
                      llm=LLMSpec("stub", "stub:8"), head_hidden=32, tensorboard=False, device=device,
                      update_epochs=2, num_minibatches=2, heads_bf16=False))
    pool = FakePool(cfg.num_envs)
    trainer = Trainer(cfg.resolved(), pool, FakeProvider(len(pool.action_names), cfg.embedding_dim))
    return trainer, trainer.train()


@pytest.mark.gpu
@pytest.mark.parametrize("method", ["ppo", "illm", "rnd", "ngu", "apt"])
def test_training_on_cuda_runs_every_hook_and_tracks_the_cpu_run(tmp_path, method):
    """The same seed on the CPU and on the GPU: every hook runs with the policy, the bonus's models
    and the rollout on the GPU, and the first update's losses agree (the kernels differ, so later
    updates drift apart)."""
    gpu, on_gpu = _short_run(tmp_path, "gpu", method, "cuda")
    cpu, on_cpu = _short_run(tmp_path, "cpu", method, "cpu")
    assert next(gpu.net.parameters()).device.type == "cuda"
    first = [json.loads(line) for line in (tmp_path / "gpu" / "metrics.jsonl").read_text().splitlines()][0]
    reference = [json.loads(line) for line in (tmp_path / "cpu" / "metrics.jsonl").read_text().splitlines()][0]
    assert first["charts/episodes"] == reference["charts/episodes"]  # the same actions: sampled on the CPU
    assert np.isclose(first["losses/value_loss"], reference["losses/value_loss"], rtol=1e-3, atol=1e-5)
    assert on_gpu["global_step"] == on_cpu["global_step"] == 256


def test_a_run_begun_on_a_gpu_resumes_on_the_devices_of_the_machine_it_resumes_on(tmp_path):
    """A grid begun on a GPU machine records device "cuda"; resumed where no --device is given on a
    machine without one, the run chooses its devices again (auto), so it resumes on a CPU machine
    instead of refusing to start; a recorded device the machine has is kept.
    A device given on resume still wins; a setting that changes what it learns is still refused."""
    from illm_tools.rl import TrainConfig
    from illm_tools.rl.build import resumed

    run = tmp_path / "run"
    run.mkdir()
    recorded = TrainConfig(run_dir=run, method="ppo", total_steps=128, device="auto").flat()
    (run / "config.json").write_text(json.dumps({**recorded, "run_dir": str(run), "device": "cuda",
                                                 "llm_device": "cuda"}))
    cfg = resumed(run, {"total_steps": 256}, ["total_steps"])
    assert cfg.device == "auto" and cfg.llm.device is None and cfg.total_steps == 256
    assert cfg.resolved().device == ("cpu" if NO_GPU else "cuda")
    assert resumed(run, {"device": "cpu"}, ["device"]).device == "cpu"
    on_cpu = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**on_cpu, "device": "cpu", "llm_device": "cpu"}))
    assert resumed(run, {}, []).device == "cpu"  # a recorded device the machine has is kept
    with pytest.raises(UsageError, match="--seed"):
        resumed(run, {"seed": 7}, ["seed"])
