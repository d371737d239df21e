"""Issue 69, finding 1 (adoption): a cache row's `model` is an identity, never where a request goes
or which secret rides with it. A cache whose rows name `m@http://127.0.0.1:P/v1#SECRET_VAR` is
adopted by `illm train` and `illm serve` without model options: a real listener on P must never
receive a request, nor the variable's value; the user's own --endpoint and --api-key-env reach the
adopted model."""

from __future__ import annotations

import socket
import threading

import pytest
from typer.testing import CliRunner

from cli.main import app
from fakes import STUB_MODEL, serve_state
from illm_tools.annotate.engine import Annotator
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.llm.stub import StubBackend

SECRET = "s3cret-value-of-the-importer"
runner = CliRunner()


class Listener:
    """A TCP listener on 127.0.0.1 that records every byte it is sent and answers 404."""

    def __init__(self):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.received = b""
        self.connections = 0
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.connections += 1
            with conn:
                conn.settimeout(2)
                try:
                    self.received += conn.recv(65536)
                    conn.sendall(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                except OSError:
                    pass

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def listener():
    lis = Listener()
    yield lis
    lis.close()


def victim_cache(root, spec: str, n: int = 4):
    """A cache of `n` states written through the project's own writing path, its rows naming `spec`."""
    cache = AnnotationCache(root)
    Annotator(StubBackend(STUB_MODEL), cache, model=spec, history_len=0).annotate_states(
        [serve_state(i) for i in range(n)], "BabyAI-GoToLocal-v0", "babyai-text@1")
    return cache


KEYS = [("#SECRET_VAR", "SECRET_VAR"), ("", "OPENAI_API_KEY")]  # a named variable, and the default one


@pytest.mark.parametrize("suffix,var", KEYS)
def test_train_never_reaches_the_address_a_caches_rows_name(tmp_path, monkeypatch, listener, suffix, var):
    monkeypatch.setenv(var, SECRET)
    victim_cache(tmp_path / "victim", f"m@http://127.0.0.1:{listener.port}/v1{suffix}")
    out = runner.invoke(app, ["train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--cache",
                              str(tmp_path / "victim"), "--live-budget", "0", "--num-envs", "2", "--num-steps", "32",
                              "--frames", "64", "--device", "cpu", "--out", str(tmp_path / "run")])
    assert (listener.connections, listener.received) == (0, b"")
    assert out.exit_code == 1 and "give --endpoint URL" in out.output and "Traceback" not in out.output
    assert str(listener.port) not in out.output and SECRET not in out.output  # no address suggested either
    assert not (tmp_path / "run" / "config.json").exists()


@pytest.mark.parametrize("suffix,var", KEYS)
def test_serve_never_reaches_the_address_a_caches_rows_name(tmp_path, monkeypatch, listener, suffix, var):
    from illm_tools.tasks.annotation_setup import adopt_model

    monkeypatch.setenv(var, SECRET)
    cache = victim_cache(tmp_path / "victim", f"m@http://127.0.0.1:{listener.port}/v1{suffix}")
    with pytest.raises(UsageError, match="give --endpoint URL"):
        adopt_model(cache)
    out = runner.invoke(app, ["serve", "--cache", str(tmp_path / "victim"), "--port", "0"])
    assert (listener.connections, listener.received) == (0, b"")
    assert out.exit_code == 1 and "give --endpoint URL" in out.output and "Traceback" not in out.output
    assert str(listener.port) not in out.output
    mine = runner.invoke(app, ["serve", "--cache", str(tmp_path / "victim"), "--port", "0", "--endpoint",
                               "http://127.0.0.1:9/v1"])  # the user's own (closed) port: tried there, and only there
    assert mine.exit_code == 1 and "no OpenAI-compatible server answers at http://127.0.0.1:9/v1" in mine.output
    assert (listener.connections, listener.received) == (0, b"")


def test_the_users_own_endpoint_and_key_reach_an_adopted_model(tmp_path, monkeypatch, listener):
    """The legitimate flow: the served name adopted, reached at the user's --endpoint with the key of
    the user's --api-key-env; the rows' address and variable are never read."""
    from illm_tools.llm.openai_wire import parse_spec
    from illm_tools.llm.spec import LLMSpec
    from illm_tools.rl.build import run_config
    from illm_tools.tasks.annotation_setup import adopt_model

    monkeypatch.setenv("SECRET_VAR", SECRET)
    cache = victim_cache(tmp_path / "victim", f"m@http://127.0.0.1:{listener.port}/v1#SECRET_VAR")
    mine = "http://127.0.0.1:9/v1"
    said = []
    settings = {"env_id": "BabyAI-GoToLocal-v0", "method": "illm", "run_dir": tmp_path / "run",
                "cache": tmp_path / "victim", "endpoint": mine, "api_key_env": "MY_KEY"}
    cfg = run_config(settings, {"env_id", "method", "run_dir", "cache", "endpoint", "api_key_env"}, say=said.append)
    assert (cfg.llm.backend, cfg.llm.model, cfg.setup.history_len) == ("openai", f"m@{mine}#MY_KEY", 0)
    assert parse_spec(cfg.llm.model) == ("m", mine, "MY_KEY")
    assert said == [f"adopting the cache's setup: --backend openai --model m --endpoint {mine} --history 0 --layout "
                    "shared (4 states answered for every task; give any of these options to choose another)"]
    held = adopt_model(cache, {"endpoint": mine})
    assert LLMSpec(**held).model == f"m@{mine}"  # the default key variable, not the rows' SECRET_VAR
    pooled = victim_cache(tmp_path / "pooled", f"m@http://127.0.0.1:{listener.port}/v1;embed=http://127.0.0.1:"
                                               f"{listener.port}/v1")
    with pytest.raises(UsageError, match="give --embed-endpoint URL"):  # its embedder is the user's to name too
        adopt_model(pooled, {"endpoint": mine})
    assert LLMSpec(**adopt_model(pooled, {"endpoint": mine, "embed_endpoint": mine})).model == f"m@{mine};embed={mine}"
    with pytest.raises(UsageError, match="give --endpoint URL"):  # a key variable alone says where nothing goes
        run_config({**settings, "endpoint": None}, {"env_id", "method", "run_dir", "cache", "api_key_env"})
    assert (listener.connections, listener.received) == (0, b"")


def test_a_listing_of_several_setups_suggests_no_address(tmp_path, listener):
    from illm_tools.tasks.annotation_setup import adopt, adopt_model, listed_setups

    cache = victim_cache(tmp_path / "victim", f"m@http://127.0.0.1:{listener.port}/v1#SECRET_VAR")
    Annotator(StubBackend("stub:32"), cache, model="stub:32", history_len=0).annotate_states(
        [serve_state(i) for i in range(2)], "BabyAI-GoToLocal-v0", "babyai-text@1")
    for refuse in (lambda: adopt(cache, ("action", "summary"), "babyai-text@1"), lambda: adopt_model(cache)):
        with pytest.raises(UsageError) as e:
            refuse()
        assert "--backend openai --model m --endpoint URL" in str(e.value) and str(listener.port) not in str(e.value)
    listed = {u["model_options"] for u in listed_setups(cache)}  # `illm cache info` (its "served at": a record)
    assert listed == {"--backend openai --model m --endpoint URL", "--backend stub --model stub:32 --dtype float32 "
                      "--quant none"}
