"""`illm serve` against its own clients (issue 47), each through HTTP against a server on 127.0.0.1
with the stub backend (run in a thread of this process, so a test can look inside it): every field
bounded and checked on arrival against the server's own setup; a state failing in the engine costs
no other state; round-robin across clients with caps per client; connections capped, stalled ones
cut off, cross-origin and other-host posts refused; a declared setup other than the server's
refused and the cache left with one setup; malformed JSON of any shape a 400 in one line."""

from __future__ import annotations

import base64
import json
import logging
import secrets
import socket
import threading
import time

import numpy as np
import pytest

from illm_tools.cache import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.llm.spec import LLMSpec
from illm_tools.llm.stub import StubBackend
from illm_tools.serve import AnnotationServer, RequestError, ServeLimits, record_to_json, token_bits
from illm_tools.tasks.state import StateRecord
from fakes import SHORT_ACTIONS as ACTIONS, STUB_LLM as LLM, STUB_MODEL as MODEL, hop_states, wait_for
from fakes import running_server as running, serve_request as request, serve_state as state
from fakes import QuietHandler, call, cli_ok as ok, server_stats as stats, stub_server as make

HOP = {"renderer": "hop@2:seed=0:beta=100.0:window=2", "history_len": 1, "env_id": "MiniGrid-MultiRoom-N6-v0"}


def frame_json(array: np.ndarray) -> dict:
    return {"shape": list(array.shape), "dtype": array.dtype.str, "data": base64.b64encode(array.tobytes()).decode()}


def oversized(kind: str) -> dict:
    """A request with one field beyond the server's limits (or its setup)."""
    one = record_to_json(state(1))
    if kind == "mission":
        one["mission"] = "m" * 8193
    elif kind == "observation":
        one["observation"] = "o" * 100_000
    elif kind == "history":
        one["history"] = [["seen", "go forward"]] * 2
    elif kind == "actions":
        one["valid_actions"] = [f"act {i}" for i in range(65)]
    elif kind == "action":
        one["valid_actions"] = ["a" * 65, "go forward"]
    elif kind == "visits":
        one["visits"] = 10**300
    if kind in ("frame_shape", "frame_dtype"):
        body = json.loads(json.dumps(request([(r, 1) for r in hop_states(1)], **HOP)))
        big = np.zeros((1024, 1024, 3), np.uint8) if kind == "frame_shape" else np.zeros((7, 7, 3), np.float64)
        body["states"][0]["frames"] = [frame_json(big)]
        return body
    if kind == "hop_on_oracle":
        return json.loads(json.dumps(request([(r, 1) for r in hop_states(1)], **HOP)))
    return {**request([]), "states": [one]}


@pytest.mark.parametrize("kind,status,says", [
    ("mission", 413, "mission has 8,193 characters"), ("observation", 413, "observation has 100,000 characters"),
    ("history", 400, "more than the server's --history 0"), ("actions", 413, "65 valid actions"),
    ("action", 413, "a valid action has 65 characters"), ("visits", 400, "visits must be a whole number"),
    ("frame_shape", 400, "a hop frame of this env is [7, 7, 3] uint8"),
    ("frame_dtype", 400, "a hop frame of this env is [7, 7, 3] uint8"),
    ("hop_on_oracle", 400, "the oracle backend reads the text"),
])
def test_every_field_is_bounded_and_checked_on_arrival(tmp_path, kind, status, says):
    hop = kind.startswith(("frame", "hop"))
    server = make(tmp_path, history_len=1 if hop else 0, llm=LLMSpec(backend="oracle") if kind == "hop_on_oracle" else LLM)
    with running(server) as url:
        code, answer = call(url + "/annotate", oversized(kind))
        assert (code, says in answer["error"]) == (status, True), answer
        assert len(answer["error"].splitlines()) == 1
        assert stats(url)["queue"] == 0
    assert not server.annotator._hop  # no projection built for a refused frame: the server's memory unchanged


class EngineStub(StubBackend):
    """The stub, each call waiting for `gate` (a test holds the engine while it queues requests) and
    failing on any prompt that mentions POISON (a state the engine cannot take)."""

    gate = threading.Event()

    def _check(self, texts) -> None:
        assert self.gate.wait(30)
        if any("POISON" in t for t in texts):
            raise RuntimeError("the engine cannot take this state")

    def score(self, contexts, *args, **kwargs):
        self._check(contexts)
        return super().score(contexts, *args, **kwargs)

    def generate(self, prompts, *args, **kwargs):
        self._check(prompts)
        return super().generate(prompts, *args, **kwargs)

    def score_and_generate(self, contexts, candidates, prompts, *args, **kwargs):
        self._check(list(contexts) + list(prompts))
        return super().score_and_generate(contexts, candidates, prompts, *args, **kwargs)


def held_engine(tmp_path) -> AnnotationServer:
    """A server whose engine waits for `EngineStub.gate`, and records the states of each batch."""
    EngineStub.gate = threading.Event()
    server = make(tmp_path, lm=EngineStub(MODEL))
    server.batches = []
    annotate = server.annotator.annotate_states  # called once per batch (one setup), then per state on a fault

    def recorded(records, *args, **kwargs):
        server.batches.append({f"{r.mission}: {r.observation}" for r in records})
        return annotate(records, *args, **kwargs)

    server.annotator.annotate_states = recorded
    return server


def test_a_state_failing_in_the_engine_costs_no_other_state(tmp_path):
    server = held_engine(tmp_path)
    server.chunk = 16
    poison = StateRecord("go to the POISON ball", (), "You see POISON", ACTIONS)
    with running(server) as url:
        assert call(url + "/annotate", request([(state(0), 1)], client="first"))[0] == 202
        wait_for(lambda: stats(url)["annotating"] == 1, 30, "the first batch in the engine")
        assert call(url + "/annotate", request([(poison, 10**9)], client="bad"))[0] == 202
        assert call(url + "/annotate", request([(state(i), 1) for i in range(1, 11)], client="good"))[0] == 202
        EngineStub.gate.set()
        wait_for(lambda: stats(url)["queue"] == 0 and stats(url)["batches"] == 2, 30, "the queue drained")
        assert "go to the POISON ball: You see POISON" in server.batches[1] and len(server.batches[1]) == 11  # together
        assert call(url + "/annotate", request([], client="good"))[1]["landed"] == 10
        answer = call(url + "/annotate", request([], client="bad"))[1]
        assert answer["failed"] == 1 and "the engine cannot take this state" in answer["failure"]
        s = stats(url)
        assert (s["annotated_states"], s["failed_states"]) == (11, 1)


def test_one_client_flooding_sessions_cannot_starve_another(tmp_path):
    server = held_engine(tmp_path)
    with running(server) as url:
        assert call(url + "/annotate", request([(state(0), 1)], client="first"))[0] == 202
        wait_for(lambda: stats(url)["annotating"] == 1, 30, "the first batch in the engine")
        for n in range(4):  # the flooder's sessions, most visited states
            states = [(StateRecord(f"flood {n} {i}", (), "", ACTIONS), 10**6) for i in range(16)]
            assert call(url + "/annotate", request(states, client="flood", session=f"s{n}"))[0] == 202
        more = [(StateRecord("flood more", (), "", ACTIONS), 10**6)]
        headers = {}
        code, answer = call(url + "/annotate", request(more, client="flood", session="s4"), answer_headers=headers)
        assert code == 429 and "--max-sessions" in answer["error"] and int(headers["Retry-After"]) >= 1
        fair = [(StateRecord("the fair one", (), "", ACTIONS), 1)]
        assert call(url + "/annotate", request(fair, client="fair"))[0] == 202
        EngineStub.gate.set()
        wait_for(lambda: any("the fair one: " in b for b in server.batches), 60, "the fair client's state annotated")
    assert next(i for i, b in enumerate(server.batches) if "the fair one: " in b) <= 1  # within two batches


def test_a_client_holds_at_most_its_share_of_the_queue(tmp_path):
    server = make(tmp_path, max_queue=10, max_client_share=0.5)
    with running(server) as url:
        headers = {}
        code, answer = call(url + "/annotate", request([(state(i), 1) for i in range(6)], client="greedy"),
                            answer_headers=headers)
        assert code == 429 and "beyond its share 5" in answer["error"] and "Retry-After" in headers


def test_stalled_idle_and_excess_connections_are_cut_off(tmp_path):
    server = make(tmp_path, max_connections_per_peer=3)
    with running(server, timeout=1.0) as url:
        port = int(url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port)) as stalled, \
                socket.create_connection(("127.0.0.1", port)) as idle:
            idle.settimeout(15)
            assert idle.recv(4096) == b""  # closed by the server
            cut = False
            for byte in b"POST /annotate HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Trickle: " + b"a" * 200:
                try:  # headers a byte at a time, never finished: cut off however long it keeps sending
                    stalled.sendall(bytes([byte]))
                except OSError:
                    cut = True
                    break
                stalled.settimeout(0.1)
                try:
                    if stalled.recv(4096) == b"":
                        cut = True
                        break
                except TimeoutError:
                    pass
            assert cut
        wait_for(lambda: stats(url)["connections"] == 1, 10, "the cut connections released")  # /stats's own
        held = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]
        try:
            with socket.create_connection(("127.0.0.1", port)) as extra:
                extra.settimeout(15)
                answer = extra.recv(4096).decode()
                assert answer.startswith("HTTP/1.1 503") and "--max-connections-per-peer" in answer
        finally:
            for s in held:
                s.close()
        assert stats(url)["connections_refused"] == 1


def test_cross_origin_text_plain_and_other_host_posts_are_refused(tmp_path):
    server = make(tmp_path)
    with running(server) as url:
        body = request([(state(1), 1)])
        code, answer = call(url + "/annotate", body,
                            headers={"Content-Type": "text/plain", "Origin": "http://evil.example"})
        assert code == 403 and "cross-origin" in answer["error"]
        code, answer = call(url + "/annotate", body, headers={"Content-Type": "text/plain"})
        assert code == 415 and "application/json" in answer["error"]
        code, answer = call(url + "/annotate", body, headers={"Host": "evil.example:80"})  # DNS rebinding
        assert code == 403 and "Host" in answer["error"]
        assert stats(url)["queue"] == 0
        assert call(url + "/annotate", body)[0] == 202  # the server's own trainer


def test_a_wrong_token_without_a_body_is_disconnected(tmp_path):
    token = secrets.token_urlsafe(32)
    server = make(tmp_path)
    with running(server, token=token) as url:
        port = int(url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.sendall(b"GET /stats HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer nope\r\n\r\n")
            s.settimeout(15)
            got = b""
            while chunk := s.recv(4096):
                got += chunk
            assert got.startswith(b"HTTP/1.1 401")  # and the connection closed (recv returned b"")


def test_a_request_declaring_another_setup_is_refused_and_the_cache_keeps_one_setup(tmp_path):
    server = make(tmp_path)
    with running(server) as url:
        assert call(url + "/annotate", request([(state(1), 1)]))[0] == 202
        wait_for(lambda: stats(url)["annotated_states"] == 1, 30, "the state annotated")
        code, answer = call(url + "/annotate", request([(state(2), 1)], client="other", history_len=3, layout="paper"))
        assert code == 409 and "--history 0 (the request's 3)" in answer["error"]
        assert "--layout shared (the request's 'paper')" in answer["error"]
        assert len(answer["error"].splitlines()) == 1
    setups = json.loads(ok("cache", "info", tmp_path / "ann", "--json"))["setups"]
    assert sorted(u["task"] for u in setups) == ["action", "summary"]  # one row per task
    from illm_tools.tasks.annotation_setup import cache_setups

    assert len(cache_setups(AnnotationCache(tmp_path / "ann"), ("action", "summary"))) == 1


@pytest.mark.parametrize("raw,says", [
    (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
    (json.dumps({**request([]), "states": [{**record_to_json(state(1)), "visits": 1}]}).replace('"visits": 1', '"visits": NaN').encode(), "NaN is not JSON"),
    (json.dumps({**request([(state(1), 1)]), "tasks": 5}).encode(), "tasks must be a list"),
    (json.dumps({**request([(state(1), 1)]), "history_len": "zero"}).encode(), "history_len must be a whole number"),
    (json.dumps({**request([(state(1), 1)]), "states": {"a": 1}}).encode(), "states must be a list"),
    (json.dumps({**request([(state(1), 1)]), "client": ["x"]}).encode(), "client must be a string"),
    (b"5", "must be a JSON object"),
    (b"\xff\xfe{", "not JSON"),
])
def test_malformed_json_of_any_shape_answers_400_in_one_line(tmp_path, caplog, raw, says):
    server = make(tmp_path)
    with caplog.at_level(logging.INFO), running(server) as url:
        code, answer = call(url + "/annotate", raw=raw)
    assert code == 400 and says in answer["error"] and len(answer["error"].splitlines()) == 1, answer
    assert not [r for r in caplog.records if r.exc_info or "Traceback" in r.getMessage()]
    assert sum("refused a request" in r.getMessage() for r in caplog.records) == 1


def test_tokens_under_128_bits_are_refused():
    assert token_bits(secrets.token_urlsafe(32)) >= 128 and token_bits(secrets.token_hex(16)) >= 128
    for weak in ("a" * 64, "ab" * 32, "0123456789abcdef", "abcdefghijklmnopqrs"):
        assert token_bits(weak) < 128, weak


def test_the_server_checks_a_frame_against_its_own_env_not_the_clients_word(tmp_path):
    server = make(tmp_path, history_len=1)
    body = json.loads(json.dumps(request([(r, 1) for r in hop_states(1)], **HOP)))
    with running(server) as url:
        assert call(url + "/annotate", body)[0] == 202
        body["states"][0]["frames"][0]["data"] = body["states"][0]["frames"][0]["data"][:-4]  # bytes short of its shape
        code, answer = call(url + "/annotate", {**body, "client": "other"})
        assert code == 400 and "a hop frame of this env is [7, 7, 3] uint8" in answer["error"]


def test_the_hop_projections_the_server_keeps_are_bounded(tmp_path):
    from illm_tools.hop.context import HopTracker
    from illm_tools.serve.batch import MAX_HOP_CONTEXTS

    server = make(tmp_path, history_len=1)
    rng = np.random.default_rng(0)
    with running(server) as url:
        for n in range(2, 9):  # each number of valid actions asks for a projection of its own
            (record,) = HopTracker(1, 1, [f"act {i}" for i in range(n)]).records(
                ["get to the green goal square"], [rng.integers(0, 9, (7, 7, 3), dtype=np.uint8)])
            body = json.loads(json.dumps(request([(record, 1)], client=f"c{n}", **HOP)))
            assert call(url + "/annotate", body)[0] == 202
            wait_for(lambda: stats(url)["queue"] == 0 and stats(url)["annotating"] == 0, 30, "annotated")
        assert stats(url)["annotated_states"] == 7
    assert len(server.annotator._hop) <= MAX_HOP_CONTEXTS


def test_a_trainer_rechecks_the_servers_model_after_a_reconnect(tmp_path, caplog):
    from illm_tools.rl.live_remote import RemoteLive
    from illm_tools.tasks.annotation_setup import AnnotationSetup

    with running(make(tmp_path)) as url:
        port = int(url.rsplit(":", 1)[1])
        live = RemoteLive(url, client="run", llm=LLM, setup=AnnotationSetup("BabyAI-GoToLocal-v0", "babyai-text@1",
                                                                            history_len=0), budget=8, max_backoff=0.5)
        live.submit([state(1)], [1])
        wait_for(lambda: live.counts["accepted"] == 1, 30, "the first list accepted")
    with caplog.at_level(logging.WARNING, logger="illm_tools.rl.live"):
        live.submit([state(2)], [1])
        wait_for(lambda: live.counts["unanswered"] >= 1, 30, "the server gone")
        other = LLMSpec(backend="stub", model="stub:24", dtype="float32")
        with running(make(tmp_path / "other", lm=StubBackend("stub:24"), llm=other), port=port) as url2:
            wait_for(lambda: live.counts["refused"] >= 1, 30, "the changed server noticed")
            assert stats(url2)["refused"] == 0 and stats(url2)["requests"] == 0  # nothing sent to it
        live.close(timeout=0.5)
    said = [r.getMessage() for r in caplog.records if "answers again but" in r.getMessage()]
    assert len(said) == 1 and "another model setup" in said[0]


def test_a_trainer_says_once_which_of_its_states_the_engine_could_not_annotate(tmp_path, caplog):
    from illm_tools.rl.live_remote import RemoteLive
    from illm_tools.tasks.annotation_setup import AnnotationSetup

    server = held_engine(tmp_path)
    EngineStub.gate.set()
    poison = StateRecord("go to the POISON ball", (), "You see POISON", ACTIONS)
    with running(server) as url, caplog.at_level(logging.WARNING, logger="illm_tools.rl.live"):
        live = RemoteLive(url, client="run", llm=LLM, setup=AnnotationSetup("BabyAI-GoToLocal-v0", "babyai-text@1",
                                                                            history_len=0), budget=8)
        live.submit([poison, state(1)], [1, 1])
        wait_for(lambda: stats(url)["failed_states"] == 1 and stats(url)["queue"] == 0, 30, "the poison failed")
        for n in range(2, 4):  # the next rollouts' requests carry the answer, once
            live.submit([state(n)], [1])
            wait_for(lambda: live.counts["accepted"] == n, 30, "accepted")
        live.close(timeout=0.5)
    said = [r.getMessage() for r in caplog.records if "could not annotate" in r.getMessage()]
    assert len(said) == 1 and "the engine cannot take this state" in said[0] and live.counts["failed"] == 1


def test_the_trainers_client_clamps_retry_after_follows_no_redirect_and_survives_a_bad_answer(caplog):
    """The trainer's serve client (`RemoteLive`): a Retry-After of inf or 1e9 waits at most 60 s; an
    answer that is not an object is said once and the sender goes on; a redirect is not followed, so
    the token never reaches the other address."""
    import http.server
    import json as _json

    from illm_tools.annotate.wire import PROTOCOL
    from illm_tools.rl.live_remote import RETRY_AFTER, RemoteLive, retry_after
    from illm_tools.tasks.annotation_setup import AnnotationSetup

    assert [retry_after(v) for v in ("inf", "1e9", "nan", "-3", "x", None, "7")] == [60.0, 60.0, 1.0, 1.0, 5.0, 5.0, 7.0]
    elsewhere: list = []  # requests that reached the redirect's target

    class Other(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # where urllib's default handling would take a POST answered 302
            elsewhere.append(self.headers.get("Authorization"))
            self.send_response(200)
            self.send_header("Content-Length", "2")
            self.end_headers()
            self.wfile.write(b"{}")

        do_POST = do_GET

        def log_message(self, *args):
            pass

    other = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Other)
    answers = [(503, {"Retry-After": "inf"}, b"{}"), (202, {}, b"[1, 2]"),
               (302, {"Location": f"http://127.0.0.1:{other.server_port}/annotate"}, b"")]

    class Fake(QuietHandler):
        def do_GET(self):  # /stats: an illm server of the stub's setup
            self.reply(200, _json.dumps({"protocol": PROTOCOL, "model_fingerprint": LLM.fingerprint(),
                                         "limits": {"max_states": 64}}).encode())

        def do_POST(self):
            self.rfile.read(int(self.headers["Content-Length"]))
            status, headers, body = answers.pop(0) if answers else (202, {}, b'{"queued": 1, "queue": 1, "landed": 0}')
            self.reply(status, body, headers)

    fake = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Fake)
    for s in (fake, other):
        threading.Thread(target=s.serve_forever, daemon=True).start()
    try:
        with caplog.at_level(logging.WARNING, logger="illm_tools.rl.live"):
            live = RemoteLive(f"http://127.0.0.1:{fake.server_port}", client="run", llm=LLM, token="t" * 40,
                              setup=AnnotationSetup("BabyAI-GoToLocal-v0", "babyai-text@1", history_len=0), budget=8)
            live.max_backoff = 0.05  # the pauses the answers below ask for, shortened (Retry-After is not)
            assert live._send([{"x": 1}]) == RETRY_AFTER[1]  # 503 with Retry-After: inf -> at most 60 s
            assert live._send([{"x": 1}]) == 0.05 and live.counts["refused"] == 1  # a list: said, the run goes on
            assert live._send([{"x": 1}]) == 0.05 and live.counts["refused"] == 2  # 302: not followed
            assert live._send([{"x": 1}]) is None and live.counts["accepted"] == 1  # and it sends again
            live.close(timeout=0.5)
        assert elsewhere == []  # the token went nowhere else
        said = [r.getMessage() for r in caplog.records]
        assert sum("not an illm server's answer" in m for m in said) == 1, said
        assert sum("answered a redirect (302)" in m for m in said) == 1, said
    finally:
        fake.shutdown()
        other.shutdown()


def test_peers_are_counted_by_group_headers_have_their_own_timeout_and_nothing_is_decompressed(tmp_path):
    import zlib

    from illm_tools.serve.config import peer_group

    assert {peer_group(a) for a in ("127.0.0.1", "127.0.0.5", "::1", "::ffff:127.0.0.9")} == {"loopback"}
    assert peer_group("10.1.2.3") == peer_group("10.1.2.250") == "10.1.2.0/24" != peer_group("10.1.3.1")
    assert peer_group("2001:db8::1") == peer_group("2001:db8::ffff:1") == "2001:db8::/64"
    server = make(tmp_path, max_connections_per_peer=3, header_timeout=1.0)
    with running(server) as url:  # the request timeout stays 30 s: an idle connection is kept
        port = int(url.rsplit(":", 1)[1])
        held = [socket.create_connection(("127.0.0.1", port), source_address=(f"127.0.0.{k}", 0)) for k in (2, 3, 4)]
        try:  # three loopback addresses are one peer: a fourth connection from a fifth is refused
            with socket.create_connection(("127.0.0.1", port), source_address=("127.0.0.5", 0)) as extra:
                extra.settimeout(15)
                assert extra.recv(4096).decode().startswith("HTTP/1.1 503")
            held[0].sendall(b"POST /annotate HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")  # headers begun, never ended
            held[0].settimeout(15)
            assert held[0].recv(4096) == b""  # cut by the header timeout (1 s), not the request timeout (30 s)
            held[1].settimeout(0.5)
            with pytest.raises(TimeoutError):  # idle, sending nothing: kept past the header timeout
                time.sleep(2.0)
                held[1].recv(4096)
        finally:
            for s in held:
                s.close()
        packer = zlib.compressobj(9)  # 256 MiB of JSON in ~250 KiB, made a MiB at a time (never held whole here)
        bomb = packer.compress(b"[") + b"".join(packer.compress(b" " * 2**20) for _ in range(256))
        bomb += packer.compress(b"]") + packer.flush()
        before = stats(url)["resident_mb"]
        code, answer = call(url + "/annotate", raw=bomb, headers={"Content-Encoding": "deflate"})
        assert code == 415 and "must not be compressed" in answer["error"]
        assert stats(url)["resident_mb"] - before < 64  # nothing was inflated
        body = request([(state(1), 1)])
        for field, value, said in (("model_fingerprint", ["f"] * 10_000, "model_fingerprint must be a string"),
                                   ("wait", "1e400", "1e400 is not a finite number")):
            raw = json.dumps({**body, field: value}).replace('"1e400"', "1e400").encode()
            code, answer = call(url + "/annotate", raw=raw)
            assert code == 400 and said in answer["error"], answer


def test_a_max_request_size_too_small_for_one_state_is_refused_at_start():
    with pytest.raises(UsageError, match="--max-request-mb 1e-07 cannot hold one state"):
        ServeLimits(max_request_mb=1e-7)


def test_a_peer_inventing_client_names_takes_one_turn_and_its_share_while_anothers_states_land(tmp_path):
    """Quotas that hold against invented names: a peer's names share its turn of each round and its
    share of the queue and of the trainer slots (`--max-peer-share`), whatever names it sends under."""
    server = make(tmp_path, max_queue=64, max_clients=16, max_sessions=4)
    flood = "10.0.0.0/24"
    accepted = 0
    for n in range(40):  # invented names, each a fresh client with states the others do not have
        states = [(StateRecord(f"flood {n} {i}", (), "", ACTIONS), 10**6) for i in range(8)]
        try:
            server.submit(request(states, client=f"name-{n}", session="s"), peer=flood)
            accepted += 1
        except RequestError as e:
            assert e.status == 429 and "--max-peer-share" in str(e), str(e)
    assert accepted == 4 and server.queue_size() == 32  # half the queue: the peer's share, not more
    fair = [(StateRecord("the fair one", (), f"You see {i}", ACTIONS), 1) for i in range(4)]
    assert server.submit(request(fair, client="fair"), peer="10.0.9.0/24")["queued"] == 4  # room left for others
    first, second = server.next_batch(), server.next_batch()
    landed = sum(p.record.mission == "the fair one" for p in first + second)
    assert landed == 4 and sum(p.record.mission == "the fair one" for p in first) == 4  # one turn each: 4 of 8
