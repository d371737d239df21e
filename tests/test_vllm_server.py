"""`VLLMServer.wait` knows its own server: another server answering at the port it was given (a port
`free_port` handed out elsewhere too) is never taken for it, and a server that could not bind it is
started again on a new port. The servers here are stand-ins (a few lines of http.server listing the
names they were started with): what is tested is the waiting, not vLLM."""

from __future__ import annotations

import subprocess
import sys
import time
import urllib.request

import pytest

from illm_tools.llm import vllm_server
from illm_tools.llm.vllm_server import EngineError, VLLMServer

STAND_IN = """
import json, sys
from http.server import BaseHTTPRequestHandler, HTTPServer
names = sys.argv[2:]
class Models(BaseHTTPRequestHandler):
    def do_GET(self):
        body = json.dumps({"data": [{"id": n} for n in names]}).encode()
        self.send_response(200); self.end_headers(); self.wfile.write(body)
    def log_message(self, *args):
        pass
HTTPServer(("127.0.0.1", int(sys.argv[1])), Models).serve_forever()  # exits at once if the port is taken
"""


def _serving(names: list[str]) -> tuple[subprocess.Popen, int]:
    """Another server (the stand-in) listing `names` at /v1/models, on a free port: (its process, the port)."""
    port = vllm_server.free_port()
    process = subprocess.Popen([sys.executable, "-c", STAND_IN, str(port), *names])
    while process.poll() is None:  # until it answers, or exits (its port taken): no deadline to miss
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/v1/models", timeout=60).close()
            return process, port
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"the stand-in server exited ({process.returncode}): port {port} taken")


@pytest.fixture
def stand_in(monkeypatch):
    """`VLLMServer.start` starts the stand-in on the server's port with its served names."""
    def start(self):
        self.process = subprocess.Popen([sys.executable, "-c", STAND_IN, str(self.port), self.served_name, self.identity],
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return self.url

    monkeypatch.setattr(VLLMServer, "start", start)


def _server(port=None):
    return VLLMServer("weights", served_name="smol", python=sys.executable, port=port)


def test_a_server_that_found_its_port_taken_starts_again_on_a_new_one(stand_in, monkeypatch):
    other, taken = _serving(["smol"])  # the same served name, another server
    ports, free_port = iter([taken]), vllm_server.free_port
    monkeypatch.setattr(vllm_server, "free_port", lambda: next(ports, None) or free_port())  # the taken one first
    server = _server()
    assert server.port == taken
    server.start()
    try:
        url = server.wait()  # ends when this server answers: the default time is only a guard
        assert url != f"http://127.0.0.1:{taken}/v1" and url == server.url
    finally:
        server.process.kill()
        other.kill()


def test_a_server_given_a_taken_port_says_another_answers_there(stand_in):
    other, taken = _serving(["smol"])
    server = _server(port=taken)  # a port the caller chose: not changed
    server.start()
    try:
        with pytest.raises(EngineError, match="another server answers at port"):
            server.wait()  # ends when the stand-in exits, its port taken
    finally:
        other.kill()

