"""Hub models (`illm_tools.llm.hub`): downloaded where the machine is online, never where it is
offline, one line for each way a download fails, and a cached snapshot used without the network.
The hub here is `tests.fakes.fake_hub`, a local server speaking the routes `snapshot_download`
calls, so the real client downloads real files."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from illm_tools.errors import ModelNotFoundError
from illm_tools.llm import hub
from illm_tools.llm.loading import load_model
from illm_tools.llm.spec import LLMSpec
from fakes import fake_hub

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def online(tmp_path, monkeypatch):
    """An online machine with an empty hub cache under tmp_path (HF_HUB_OFFLINE unset)."""
    from huggingface_hub import constants

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.delenv("TRANSFORMERS_OFFLINE", raising=False)
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)  # read once at import (conftest sets it)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    return tmp_path


def _closed_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed again when the block ends: nothing listens there


def test_a_hub_model_downloads_when_online_and_is_then_used_from_the_cache(online, monkeypatch, tiny_lm, caplog):
    repo = online / "repo"
    shutil.copytree(tiny_lm.spec.path, repo)
    (repo / "pytorch_model.bin").write_bytes(b"a second copy of the weights, not fetched beside safetensors")
    with fake_hub({"org/tiny": repo}) as url:
        monkeypatch.setenv("HF_ENDPOINT", url)
        with caplog.at_level(logging.INFO, logger="illm_tools"):
            lm = load_model("org/tiny", dtype="float32", cache_dir=online / "illm")
        assert fake_hub.requests > 0
        snapshot = Path(lm.spec.model_id and hub.cached("org/tiny"))
        assert lm.fingerprint["revision"] == snapshot.name and len(snapshot.name) == 40
        assert (snapshot / "model.safetensors").is_file() and not (snapshot / "pytorch_model.bin").exists()
        assert any(r.getMessage().startswith("downloading org/tiny from " + url) for r in caplog.records)
        before = fake_hub.requests
        again = load_model("org/tiny", dtype="float32", cache_dir=online / "illm")
        assert fake_hub.requests == before  # a cached snapshot is used as it is: no network call
        assert again.fingerprint == lm.fingerprint
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    assert load_model("org/tiny", dtype="float32", cache_dir=online / "illm").fingerprint == lm.fingerprint


def test_offline_never_asks_the_hub(online, monkeypatch, tiny_lm):
    with fake_hub({"org/tiny": Path(tiny_lm.spec.path)}) as url:
        monkeypatch.setenv("HF_ENDPOINT", url)
        with pytest.raises(ModelNotFoundError, match="--offline was given.*hf download org/tiny"):
            LLMSpec(model="org/tiny", offline=True, dtype="float32").load(cache_dir=str(online / "illm"))
        monkeypatch.setenv("HF_HUB_OFFLINE", "1")
        with pytest.raises(ModelNotFoundError, match="HF_HUB_OFFLINE is set"):
            LLMSpec(model="org/tiny", dtype="float32").load(cache_dir=str(online / "illm"))
        with hub.no_downloads(), pytest.raises(ModelNotFoundError, match="downloads nothing|list or describe"):
            monkeypatch.delenv("HF_HUB_OFFLINE")
            hub.snapshot(["org/tiny"])
        assert fake_hub.requests == 0


@pytest.mark.parametrize("refusal, says", [
    ((403, "GatedRepo"), "gated model: accept its licence.*HF_TOKEN or run `hf auth login`"),
    ((404, "RepoNotFound"), "no model 'org/gone' on the hub.*check the id"),
])
def test_a_gated_or_missing_repository_is_one_line(online, monkeypatch, tiny_lm, refusal, says):
    with fake_hub({}, refuse={"org/gone": refusal}) as url:
        monkeypatch.setenv("HF_ENDPOINT", url)
        with pytest.raises(ModelNotFoundError, match=says) as raised:
            load_model("org/gone", dtype="float32", cache_dir=online / "illm")
    assert "\n" not in str(raised.value)
    assert not (online / "hub" / "models--org--gone" / "snapshots").exists()


def test_too_little_disk_is_refused_before_downloading(online, monkeypatch, tiny_lm):
    real = shutil.disk_usage

    def nearly_full(path):
        return real(path)._replace(free=1000)

    monkeypatch.setattr(hub.shutil, "disk_usage", nearly_full)
    with fake_hub({"org/tiny": Path(tiny_lm.spec.path)}) as url:
        monkeypatch.setenv("HF_ENDPOINT", url)
        with pytest.raises(ModelNotFoundError, match=r"downloading org/tiny needs .* and .* has 1\.0 KB free.*HF_HUB_CACHE"):
            load_model("org/tiny", dtype="float32", cache_dir=online / "illm")
    assert not (online / "hub" / "models--org--tiny" / "snapshots").exists()


def test_an_unreachable_hub_is_a_network_error_not_offline(tmp_path, tiny_lm):
    """What a user runs: `illm annotate --model org/name` with HF_HUB_OFFLINE unset and a hub that does not
    answer (HF_ENDPOINT on a closed port): one line that names the hub, exit 1, nothing in the cache."""
    from illm_tools.collect import CollectConfig, collect

    collect(CollectConfig(env_id="BabyAI-GoToLocal-v0", steps=8, num_envs=2, seed=0, out=tmp_path / "traj"))
    env = {k: v for k, v in os.environ.items() if k not in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")}
    env.update(HF_ENDPOINT=f"http://127.0.0.1:{_closed_port()}", HF_HUB_CACHE=str(tmp_path / "hub"),
               ILLM_CACHE_DIR=str(tmp_path / "illm"))
    done = subprocess.run([sys.executable, "-m", "cli.main", "annotate", str(tmp_path / "traj"), "--cache",
                           str(tmp_path / "ann"), "--model", "meta-llama/Meta-Llama-3-8B", "--limit", "2"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert lines[-1].startswith("error: the Hugging Face hub at http://127.0.0.1:") and "cannot be reached" in lines[-1]
    assert "offline" not in lines[-1].split("and meta-llama")[0] and "Traceback" not in done.stderr
    assert not (tmp_path / "ann").exists() or not any((tmp_path / "ann").rglob("*.arrow"))


@pytest.mark.slow
def test_a_cached_snapshot_of_the_embedded_model_loads_with_and_without_network(online, monkeypatch, smollm2_cache):
    """A real hub cache layout (blobs, snapshots linked to them, refs/main), written by the hub client
    itself from the embedded model's de-quantised weights, loads offline and online: online with the
    hub unreachable, since a cached snapshot needs no network call."""
    from illm_tools.llm.loading import dequantised_folder
    from illm_tools.llm.registry import resolve

    weights, _ = dequantised_folder(resolve("smollm2-135m"), Path(smollm2_cache))
    with fake_hub({"HuggingFaceTB/SmolLM2-135M-Instruct": weights}) as url:
        monkeypatch.setenv("HF_ENDPOINT", url)
        snapshot = hub.snapshot(["HuggingFaceTB/SmolLM2-135M-Instruct"])
    base = online / "hub" / "models--HuggingFaceTB--SmolLM2-135M-Instruct"
    assert (base / "refs" / "main").read_text() == snapshot.name and (snapshot / "model.safetensors").is_symlink()
    monkeypatch.setenv("HF_ENDPOINT", f"http://127.0.0.1:{_closed_port()}")
    online_lm = load_model("HuggingFaceTB/SmolLM2-135M-Instruct", dtype="float32", cache_dir=online / "illm")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    offline_lm = load_model("HuggingFaceTB/SmolLM2-135M-Instruct", dtype="float32", cache_dir=online / "illm")
    assert online_lm.fingerprint == offline_lm.fingerprint and online_lm.fingerprint["revision"] == snapshot.name
    assert online_lm.hidden_size == 576


def test_device_and_quantisation_default_to_the_machine_and_the_alias():
    from illm_tools.llm.backend import backend_quant
    from illm_tools.rl.config import TrainConfig

    spec = LLMSpec()
    assert spec.device is None and spec.quant == "auto"
    placed = spec.placed()
    assert placed.device == "cpu" and placed.quant == "none"  # this machine has no CUDA device
    assert TrainConfig().device == "auto" and TrainConfig().llm.quant == "auto"
    assert backend_quant("transformers", "llama3", "auto", "cuda") == "4bit"
    assert backend_quant("transformers", "meta-llama/Llama-2-7b-hf", "auto", "cuda:1") == "4bit"
    assert backend_quant("transformers", "llama3", "auto", "cpu") == "none"
    assert backend_quant("transformers", "smollm2-135m", "auto", "cuda") == "none"
    assert backend_quant("transformers", "llama3", "none", "cuda") == "none"
    assert backend_quant("oracle", "oracle", "auto", "cuda") == "none"


def test_four_bit_is_nf4_said_before_loading_and_in_the_fingerprint(tiny_lm, tmp_path, caplog):
    pytest.importorskip("bitsandbytes")
    with caplog.at_level(logging.INFO, logger="illm_tools"):
        lm = load_model(tiny_lm.spec.path, dtype="float32", quant="4bit", cache_dir=tmp_path)
    assert lm.fingerprint["quant"] == "4bit" and lm.fingerprint["quant_type"] == "nf4"
    assert lm.model.config.quantization_config.bnb_4bit_quant_type == "nf4"
    said = [r.getMessage() for r in caplog.records if "bitsandbytes" in r.getMessage()]
    assert said and "4-bit NF4" in said[0] and "--quant none" in said[0]
