"""`illm serve`'s requests and servers: the stub's setup (`STUB_MODEL`, `STUB_LLM`,
`stub_fingerprint`), its states and requests (`serve_state`, `serve_request`, `hop_states`), a server
of the stub (`stub_server`) in a thread of the test (`running_server`), `illm serve` with slow
batches (`SLOW_SERVER`), a request to a server (`call`, `server_stats`) and `wait_for`. Used by
test_serve.py, test_serve_hardening.py, test_trust_serve.py, test_trust_budget.py,
test_trust_adopt.py, test_trust_openai.py, test_engine_tokens.py and test_coverage.py."""

from __future__ import annotations

import asyncio
import functools
import json
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager

from illm_tools.keys import fingerprint_hash
from illm_tools.llm.spec import LLMSpec
from illm_tools.llm.stub import StubBackend
from illm_tools.tasks.state import StateRecord

from .prompts import SHORT_ACTIONS, state_record

STUB_MODEL = "stub:16"
STUB_LLM = LLMSpec(backend="stub", model=STUB_MODEL, dtype="float32")


@functools.cache
def stub_fingerprint() -> str:
    """The stub's fingerprint hash (built on first use: the stub resolves its dtype, which imports torch)."""
    return fingerprint_hash(StubBackend(STUB_MODEL).fingerprint)


def serve_state(i: int) -> StateRecord:
    """A BabyAI-like state of the short action list, told apart by `i`."""
    return state_record(f"You see a red ball {i} steps forward", actions=SHORT_ACTIONS)


def serve_request(pending, client="run-a", session="s1", **changes) -> dict:
    """A `POST /annotate` body of the stub's setup for `pending` [(state, visits)]; `changes` override."""
    from illm_tools.serve import record_to_json

    body = {"client": client, "session": session, "model_fingerprint": stub_fingerprint(), "env_id": "BabyAI-GoToLocal-v0", "renderer": "babyai-text@1",
            "history_len": 0, "layout": "shared", "tasks": ["action", "summary"],
            "states": [{**record_to_json(s), "visits": n} for s, n in pending]}
    body.update(changes)
    return body


def stub_server(tmp_path, lm=None, llm: LLMSpec = STUB_LLM, history_len: int = 0, **limits):
    """An `AnnotationServer` of `lm` (the stub by default) declared as `llm`, its cache at `tmp_path / "ann"`,
    prompts of `history_len` steps of history, chunks of 8 and `limits` (ServeLimits' fields) over the
    defaults: for `running_server`, or a test that drives its scheduler directly."""
    from illm_tools.cache import AnnotationCache
    from illm_tools.serve import AnnotationServer, ServeLimits
    from illm_tools.tasks.prompt_config import PromptConfig

    return AnnotationServer(lm or StubBackend(STUB_MODEL), AnnotationCache(tmp_path / "ann"), llm=llm,
                            prompt=PromptConfig(history_len=history_len), chunk=8, limits=ServeLimits(**limits))


@contextmanager
def running_server(server, *, token: str | None = None, timeout: float | None = None, port: int = 0) -> Iterator[str]:
    """`server` (an `AnnotationServer`) listening on 127.0.0.1 (a free port, or `port`) in a thread of
    its own, its URL yielded; stopped at the end. `timeout`: the request timeout (default the server's)."""
    from illm_tools.serve import serve

    ready, box = threading.Event(), {}

    async def main() -> None:
        box["stop"], box["loop"] = asyncio.Event(), asyncio.get_running_loop()
        await serve(server, "127.0.0.1", port, box["stop"], token=token, request_timeout=timeout,
                    on_ready=lambda addresses: (box.update(port=addresses[0][1]), ready.set()))

    thread = threading.Thread(target=lambda: asyncio.run(main()), daemon=True)
    thread.start()
    assert ready.wait(30), "the server did not start"
    try:
        yield f"http://127.0.0.1:{box['port']}"
    finally:
        box["loop"].call_soon_threadsafe(box["stop"].set)
        thread.join(30)


SLOW_SERVER = """
import os, sys, time
from illm_tools.llm.backend import BACKENDS
from illm_tools.llm.stub import StubBackend

class SlowStub(StubBackend):  # the stub's answers and fingerprint, each batch taking SLOW_S seconds
    def score(self, *args, **kwargs):
        time.sleep(float(os.environ["SLOW_S"]))
        return super().score(*args, **kwargs)

BACKENDS.register("slow", SlowStub)
from cli.main import main
sys.argv = ["illm", *sys.argv[1:]]
main()
"""
"""`illm serve` as `python -c SLOW_SERVER serve ... --backend slow`: the stub, each batch taking the
environment's SLOW_S seconds."""


def call(url: str, body=None, raw: bytes | None = None, token: str | None = None, headers: dict | None = None,
         answer_headers: dict | None = None, timeout: float = 60.0) -> tuple[int, dict]:
    """(status, JSON answer) of a GET (no body) or POST (`body` as JSON, or the bytes `raw`) to an
    `illm serve` server: `token` its bearer token, `headers` sent beside (over) the JSON content type;
    `answer_headers`, a dict, gets the answer's headers (a success's or a refusal's)."""
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    sent = {"Content-Type": "application/json", **({"Authorization": f"Bearer {token}"} if token else {}),
            **(headers or {})}
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data=data, method="GET" if data is None else "POST",
                                                           headers=sent), timeout=timeout) as r:
            answer = r.status, json.loads(r.read())
            got = r.headers
    except urllib.error.HTTPError as e:
        answer, got = (e.code, json.loads(e.read())), e.headers
    if answer_headers is not None:
        answer_headers.update(got)
    return answer


def server_stats(url: str, token: str | None = None) -> dict:
    """`GET /stats` of the server at `url` (its base URL), asserted answered (200): its counters."""
    status, stats = call(url + "/stats", token=token)
    assert status == 200, (status, stats)
    return stats


def wait_for(check, seconds: float = 60.0, what: str = ""):
    """Poll `check()` every 0.1 s until it returns something true (returned), at most `seconds`."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        time.sleep(0.1)
    raise AssertionError(f"not within {seconds:g} s: {what}")


def hop_states(n: int = 3):
    """Hop records of one env's first steps, as a hop trainer builds them (window 2)."""
    import numpy as np

    from illm_tools.hop.context import HopTracker

    tracker = HopTracker(1, 1, SHORT_ACTIONS)
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        (record,) = tracker.records(["get to the green goal square"], [rng.integers(0, 9, (7, 7, 3), dtype=np.uint8)])
        out.append(record)
        tracker.push([2], [False])
    return out
