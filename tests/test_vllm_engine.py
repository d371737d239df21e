"""`--backend openai` against the serving engine the docs recommend: vLLM (its CPU build, from the
engine's own environment `.venv-engine`, which `make test` builds), on 127.0.0.1 with the embedded
SmolLM2-135M's weights. Two servers of the same weights: completions (ranking by echoed prompt
log-probs, greedy summaries) and a pooling runner for the summaries' embeddings (`--embed-endpoint`).

What it checks: the engine passes illm's probes (a list of prompts in one request; echoed prompt
log-probs aligned with its generation's); its top action equals the transformers backend's on at
least 95% of 64 states (both in the dtype illm picks for this CPU); its pooled embeddings are the
transformers backend's mean hidden states of the same texts; the cache verifies; a training run's
live fallback through it lands targets. Without `.venv-engine` the module is skipped, except under
CI, where it fails."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from fakes import collected, trains_with_the_engine_stopped

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("vllm")]  # one worker starts the servers once
ROOT = Path(__file__).resolve().parents[1]
SERVED = "smol"
runner = CliRunner()


@pytest.fixture(scope="session")
def dtype():
    """The dtype illm picks on this CPU (bfloat16 where a timed matmul says it is faster): both sides use it."""
    from illm_tools.llm.dtype import resolve_dtype

    return resolve_dtype("auto")


@pytest.fixture(scope="session")
def engine_servers():
    """The `VLLMServer`s `engines` started (the last test stops them)."""
    return []


@pytest.fixture(scope="session")
def engines(smollm2_cache, tmp_path_factory, engine_servers):
    """The completions server and the pooling server of the embedded model's weights: their URLs. Session
    scope: started once in the worker that runs this module (a module's fixture is set up again when its
    tests are interleaved with another module's). `--optimization-level 0` (no torch.compile: it builds
    C++ kernels for minutes on 2 cores) starts them in seconds; the answers are the same computation."""
    from illm_tools.llm.dtype import resolve_dtype

    from illm_tools.llm.loading import dequantised_folder
    from illm_tools.llm.registry import resolve
    from illm_tools.llm.vllm_server import VLLMServer, engine_python

    python = engine_python(ROOT)
    if not python.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"no engine environment at {python}: `make test` builds it (`make engine`)")
        pytest.skip(f"no engine environment at {python}: run `make engine`")
    weights, _ = dequantised_folder(resolve("smollm2-135m"), Path(smollm2_cache))
    logs = tmp_path_factory.mktemp("engine")
    servers = [VLLMServer(weights, served_name=SERVED, python=python, runner=r, dtype=resolve_dtype("auto"),
                          log=logs / f"{r}.log", kv_cache_gib=1.0, optimization=0) for r in ("generate", "pooling")]
    engine_servers.extend(servers)
    try:
        for server in servers:  # both compile at once
            server.start()
        yield tuple(server.wait() for server in servers)
    finally:
        for server in servers:
            server.stop()


@pytest.fixture(scope="module")
def trajectories(tmp_path_factory):
    return collected(tmp_path_factory.mktemp("traj") / "traj", 400, 4)


def _annotate(trajectories, cache, *model, tasks="action", limit=64):
    done = runner.invoke(app, ["annotate", str(trajectories), "--cache", str(cache), *model, "--tasks", tasks,
                               "--history", "0", "--limit", str(limit)])
    assert done.exit_code == 0, done.output
    return done.output


def _rows(cache, task):
    from illm_tools.cache.store import AnnotationCache

    table = AnnotationCache(cache).table(["task", "prompt", "chosen_index", "text", "embedding", "model_fingerprint"])
    return {r["prompt"]: r for r in table.to_pylist() if r["task"] == task}


def test_the_engine_passes_the_probes(engines):
    from illm_tools.llm import openai_wire

    spec = openai_wire.openai_spec(SERVED, engines[0], embed_endpoint=engines[1])
    fingerprint = openai_wire.served_fingerprint(spec)
    assert fingerprint["engine"] == "version 0.32.0"  # vLLM's /version; one prompt list per request
    probe = openai_wire.engine_probe(spec)
    assert probe.batches and probe.aligned, probe.detail
    assert fingerprint["embedder"].startswith("pooling endpoint") and fingerprint["embedding_dim"] == 576


def test_its_ranking_is_the_transformers_backends(engines, trajectories, dtype, tmp_path, smollm2_cache):
    served = ["--backend", "openai", "--model", SERVED, "--endpoint", engines[0]]
    _annotate(trajectories, tmp_path / "vllm", *served)
    os.environ["ILLM_CACHE_DIR"] = str(smollm2_cache)  # the de-quantised weights the engine serves
    try:
        _annotate(trajectories, tmp_path / "local", "--model", "smollm2-135m", "--dtype", dtype, "--device", "cpu")
    finally:
        del os.environ["ILLM_CACHE_DIR"]
    vllm, local = _rows(tmp_path / "vllm", "action"), _rows(tmp_path / "local", "action")
    assert len(vllm) == len(local) == 64 and set(vllm) == set(local)  # the same prompts
    same = sum(vllm[p]["chosen_index"] == local[p]["chosen_index"] for p in vllm)
    assert same >= 0.95 * 64, f"the top action agrees on {same} of 64 states"
    done = runner.invoke(app, ["cache", "verify", str(tmp_path / "vllm")])
    assert done.exit_code == 0, done.output


def test_its_pooled_embeddings_are_the_models_mean_hidden_states(engines, trajectories, dtype, tmp_path,
                                                                 smollm2_cache):
    from illm_tools.llm.generation import embed_texts
    from illm_tools.llm.loading import load_model

    _annotate(trajectories, tmp_path / "ann", "--backend", "openai", "--model", SERVED, "--endpoint", engines[0],
              "--embed-endpoint", engines[1], tasks="summary", limit=8)
    rows = list(_rows(tmp_path / "ann", "summary").values())
    assert len(rows) == 8 and all(r["text"].strip() for r in rows)
    lm = load_model("smollm2-135m", dtype=dtype, cache_dir=smollm2_cache)
    local = embed_texts(lm, [r["text"] for r in rows])
    pooled = np.asarray([r["embedding"] for r in rows], np.float32)
    cosine = (local * pooled).sum(1) / np.linalg.norm(local, axis=1) / np.linalg.norm(pooled, axis=1)
    assert cosine.min() > 0.99, cosine


def test_a_training_runs_live_fallback_through_it_lands_targets(engines, tmp_path):
    done = runner.invoke(app, ["train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--backend", "openai",
                               "--model", SERVED, "--endpoint", engines[0], "--embed-endpoint", engines[1],
                               "--cache", str(tmp_path / "ann"), "--history", "0", "--frames", "256",
                               "--num-envs", "4", "--num-steps", "32", "--live-budget", "8", "--live-mode", "sync",
                               "--seed", "0", "--out", str(tmp_path / "run"), "--device", "cpu"])
    assert done.exit_code == 0, done.output
    from illm_tools.cache.store import AnnotationCache

    landed = AnnotationCache(tmp_path / "ann").tasks()
    assert landed.get("action", 0) >= 8 and landed.get("summary", 0) >= 8, landed
    assert "states annotated live" in done.output


def test_its_cache_trains_with_the_engines_stopped_under_either_address(engines, engine_servers, tmp_path):
    """Issue 54, last in the module (it stops the engines): annotated at 127.0.0.1, a few states more
    through `localhost`; with both servers stopped `illm cache info` lists one setup per task and
    `illm train --live-budget 0` adopts it and trains on its targets."""
    traj = collected(tmp_path / "traj", 256, 4, env="BabyAI-GoToRedBallNoDists-v0")
    ann = tmp_path / "ann"
    for url, pooled, limit in ((engines[0], engines[1], 12), (engines[0].replace("127.0.0.1", "localhost"),
                                                              engines[1].replace("127.0.0.1", "localhost"), 16)):
        _annotate(traj, ann, "--backend", "openai", "--model", SERVED, "--endpoint", url, "--embed-endpoint", pooled,
                  tasks="action,summary", limit=limit)
    for server in engine_servers:
        server.stop()
    trains_with_the_engine_stopped(ann, tmp_path / "run", 16, reach=("--endpoint", engines[0], "--embed-endpoint",
                                                                     engines[1]))
