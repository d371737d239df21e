"""`--backend openai` against a real serving engine that fails illm's alignment probe: llama-cpp-python's
OpenAI server on 127.0.0.1 with the embedded SmolLM2-135M GGUF. Opt-in: `make install` no longer builds
llama-cpp-python (PyPI has its source only: 5-10 minutes on 2 cores), so the module runs only where it is
installed (`CMAKE_ARGS=-DGGML_NATIVE=OFF pip install "llama-cpp-python[server]==0.3.36"`); the refusal
of a shifted echo is covered without it by tests/test_openai_backend.py's engine in its shifted mode.

What it shows about the pinned version: the engine takes one prompt per request (illm detects it
and sends them one at a time); its echoed prompt log-probs are shifted by one position, so ranking
through it is refused in one line before anything is written; summaries (generation) annotate
through it. If a later version aligns its echo, the ranking test fails saying so: the docs' table
of engines and this test are then to be updated, not silenced."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli.main import app
from fakes import collected

pytestmark = pytest.mark.slow
pytest.importorskip("llama_cpp", reason="opt-in: llama-cpp-python is not installed (see the module docstring)")
runner = CliRunner()
SERVED = "smollm2-gguf"


def _gguf() -> Path:
    from illm_tools.llm.registry import locate, resolve

    spec = resolve("smollm2-135m")
    return locate(spec) / spec.gguf_file  # the GGUF file the embedded model's package ships


@pytest.fixture(scope="module")
def engine(tmp_path_factory):
    """llama-cpp-python's server, started here and stopped after the module; its base URL."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = tmp_path_factory.mktemp("engine") / "server.log"
    with open(log, "w") as out:
        server = subprocess.Popen([sys.executable, "-m", "llama_cpp.server", "--model", str(_gguf()), "--model_alias",
                                   SERVED, "--host", "127.0.0.1", "--port", str(port), "--n_ctx", "1024",
                                   "--n_threads", "1", "--logits_all", "true"], stdout=out, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/v1"
    try:
        deadline = time.monotonic() + 120
        while True:  # bounded: the server loads a 100 MB model
            try:
                with urllib.request.urlopen(url + "/models", timeout=5) as answer:
                    if json.loads(answer.read())["data"]:
                        break
            except OSError:
                pass
            if server.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"llama-cpp-python's server did not start: {log.read_text()[-2000:]}")
            time.sleep(0.5)
        yield url
    finally:
        server.terminate()
        try:
            server.wait(20)
        except subprocess.TimeoutExpired:
            server.kill()


@pytest.fixture(scope="module")
def trajectories(tmp_path_factory):
    return collected(tmp_path_factory.mktemp("traj") / "traj", 16, 2)


def _annotate(trajectories, cache, engine, *extra):
    return runner.invoke(app, ["annotate", str(trajectories), "--cache", str(cache), "--backend", "openai", "--model",
                               SERVED, "--endpoint", engine, "--history", "0", "--limit", "4", *extra])


def test_ranking_through_the_engine_is_refused_in_one_line_with_nothing_written(engine, trajectories, tmp_path):
    from llama_cpp import __version__

    from illm_tools.llm.openai import OpenAIBackend
    from illm_tools.llm.openai_wire import openai_spec

    backend = OpenAIBackend(openai_spec(SERVED, engine))
    assert not backend.engine.batches and "one prompt per request" in backend.fingerprint["engine"]
    if backend.engine.aligned:
        pytest.fail(f"llama-cpp-python {__version__} now gives aligned prompt log-probs ({backend.engine.detail}): "
                    "ranking works through it; update the docs' engine table and this test")
    out = _annotate(trajectories, tmp_path / "ann", engine)
    lines = out.output.strip().splitlines()
    assert out.exit_code == 1 and "cannot rank actions" in lines[-1] and "shifted by one position" in lines[-1]
    assert "Traceback" not in out.output and "--tasks summary" in lines[-1]
    assert not (tmp_path / "ann").exists() or not list((tmp_path / "ann").glob("shard-*.arrow"))


def test_summaries_annotate_through_the_engine(engine, trajectories, tmp_path):
    out = _annotate(trajectories, tmp_path / "ann", engine, "--tasks", "summary")
    assert out.exit_code == 0, out.output
    info = runner.invoke(app, ["cache", "info", str(tmp_path / "ann"), "--json"])
    assert json.loads(info.output)["tasks"] == {"summary": 4}
    assert runner.invoke(app, ["cache", "verify", str(tmp_path / "ann")]).exit_code == 0
