"""`illm serve` holds nothing for a client that has gone, and its quotas hold against the peers
actually contending (issue 69, findings 2, 7 and 8). Each through HTTP against a server on
127.0.0.1 with the stub backend (in a thread of this process, so a test can look inside it), or
against the scheduler directly with the peer a request would come from; the memory test runs
`illm serve` as a user starts it and reads its resident memory."""

from __future__ import annotations

import asyncio
import gc
import json
import re
import secrets
import socket
import subprocess
import sys
import threading
import time

import pytest

from illm_tools.llm.stub import StubBackend
from illm_tools.serve import RequestError, ServeLimits, record_to_json
from illm_tools.tasks.state import StateRecord
from fakes import SHORT_ACTIONS as ACTIONS, SLOW_SERVER, STUB_MODEL as MODEL, wait_for
from fakes import running_server as running, serve_request as request, serve_state as state
from fakes import call, server_stats as stats, stub_server as make

V4, V6, THIRD = "203.0.113.0/24", "2001:db8:1::/64", "198.51.100.0/24"  # one dual-stack host's two groups, another


class HeldStub(StubBackend):
    """The stub, each engine call waiting for `gate` (a test holds the engine while requests wait)."""

    gate = threading.Event()

    def score_and_generate(self, *args, **kwargs):
        assert self.gate.wait(60)
        return super().score_and_generate(*args, **kwargs)

    def score(self, *args, **kwargs):
        assert self.gate.wait(60)
        return super().score(*args, **kwargs)


def raw_post(port: int, body: bytes) -> socket.socket:
    """A socket that has sent one POST /annotate with `body` and reads nothing."""
    s = socket.create_connection(("127.0.0.1", port))
    s.sendall(f"POST /annotate HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n"
              f"Content-Length: {len(body)}\r\n\r\n".encode() + body)
    return s


# --- finding 2: nothing held for a client that has gone -------------------------------------------------------


def test_fields_the_server_does_not_read_are_refused_in_one_line(tmp_path):
    server = make(tmp_path)
    with running(server) as url:
        code, answer = call(url + "/annotate", {**request([(state(1), 1)]), "pad": "x" * 1000})
        assert (code, "the request has fields this server does not read ('pad')" in answer["error"]) == (400, True)
        one = {**record_to_json(state(1)), "visits": 1, "junk": [0] * 1000}
        code, answer = call(url + "/annotate", {**request([]), "states": [one]})
        assert (code, "a state has fields this server does not read ('junk')" in answer["error"]) == (400, True)
        assert len(answer["error"].splitlines()) == 1 and stats(url)["queue"] == 0


def test_a_waiting_request_keeps_no_body_and_is_cancelled_when_its_client_leaves(tmp_path):
    HeldStub.gate = threading.Event()
    server = make(tmp_path, lm=HeldStub(MODEL))
    marker = f"MARK-{secrets.token_hex(8)}"
    twin = StateRecord("go to the red ball", (), marker, ACTIONS)
    body = json.dumps(request([(twin, 1)] * 200, wait=60)).encode()  # 200 copies of one state: one queued

    def parsed_states() -> int:  # the request's own state objects still alive (a queued record has no visits)
        gc.collect()
        return sum(1 for o in gc.get_objects() if type(o) is dict and "visits" in o and o.get("observation") == marker)

    try:
        with running(server) as url:
            port = int(url.rsplit(":", 1)[1])
            client = raw_post(port, body)
            del body
            wait_for(lambda: len(server._waiters) == 1 and server.annotating == 1, 30, "the request waiting")
            assert parsed_states() == 0  # while it waits it holds its trainer's name, not its body
            client.close()  # the client gives up
            wait_for(lambda: not server._waiters, 10, "the waiter cancelled")
            wait_for(lambda: stats(url)["connections"] == 1, 10, "its connection released")  # /stats's own
            assert stats(url)["waiting"] == 0
            HeldStub.gate.set()
    finally:
        HeldStub.gate.set()


def test_one_waiter_per_trainer_and_a_peers_waiters_capped(tmp_path):
    HeldStub.gate = threading.Event()
    server = make(tmp_path, lm=HeldStub(MODEL), max_clients=2, max_peer_share=0.5, new_peer_room=0)
    answers: dict = {}

    def waiting_post(name: str, body: dict) -> threading.Thread:
        thread = threading.Thread(
            target=lambda: answers.__setitem__(name, (call(url + "/annotate", body), time.monotonic())))
        thread.start()
        return thread

    try:
        with running(server) as url:
            first = waiting_post("first", request([(state(1), 1)], wait=60))
            wait_for(lambda: len(server._waiters) == 1 and server.annotating == 1, 30, "the first waiting")
            # the peer's one waiter is taken
            code, answer = call(url + "/annotate", request([(state(2), 1)], client="other", wait=60))
            assert code == 429 and "requests waiting" in answer["error"], answer
            second = waiting_post("second", request([(state(1), 1)], wait=60))  # the same trainer again
            first.join(30)
            (code, answer), _ = answers["first"]
            assert code == 202 and answer["pending"] is True and answer["landed"] == 0  # answered at once
            HeldStub.gate.set()
            second.join(30)
            (code, answer), _ = answers["second"]
            assert code == 202 and answer["landed"] >= 1 and answer["pending"] is False  # it took the answers
            assert server.waiting == 0
    finally:
        HeldStub.gate.set()


# --- finding 7: quotas against the peers actually contending --------------------------------------------------


def test_two_peer_groups_of_one_host_leave_room_for_a_third_peer(tmp_path):
    server = make(tmp_path)  # the defaults: 64 trainer slots, 8,192 states, half of each a peer's
    taken = {V4: 0, V6: 0}
    for peer in (V4, V6):
        for n in range(64):  # a trainer a name, until refused
            try:
                server.submit(request([(StateRecord(f"{peer} {n}", (), "", ACTIONS), 1)], client=f"{peer} {n}"), peer=peer)
                taken[peer] += 1
            except RequestError as e:
                assert e.status in (429, 503), str(e)
    assert taken == {V4: 32, V6: 24} and len(server._clients) == 56
    assert server.submit(request([(state(1), 1)], client="third"), peer=THIRD)["queued"] == 1  # served

    server = make(tmp_path / "queue")
    for peer in (V4, V6):
        for n in range(8):  # lists of 1,024 states, until refused
            states = [(StateRecord(f"{peer} {n}", (), f"{i}", ACTIONS), 1) for i in range(1024)]
            try:
                server.submit(request(states, client=f"{peer} {n}"), peer=peer)
            except RequestError as e:
                assert e.status in (429, 503), str(e)
    assert server.queue_size() == 8192 - 1024
    assert server.submit(request([(state(1), 1)], client="third"), peer=THIRD)["queued"] == 1  # served


def test_another_peer_sending_a_runs_name_takes_nothing_of_that_runs_quota(tmp_path):
    server = make(tmp_path)
    victim = request([(state(1), 1)], client="runs/victim", session="own")
    for n in range(5):  # the run's name from another peer, as many sessions as its quota holds, and one more
        body = request([(StateRecord("squat", (), f"{n}", ACTIONS), 1)], client="runs/victim", session=f"s{n}")
        try:
            server.submit(body, peer=V4)
        except RequestError as e:
            assert (n, e.status, "--max-sessions" in str(e)) == (4, 429, True)
    assert server.submit(victim, peer=THIRD)["queued"] == 1  # the run's own trainer is served
    with pytest.raises(RequestError, match="from another peer") as e:  # nor can its session be taken over
        server.submit(request([], client="runs/victim", session="own"), peer=V4)
    assert e.value.status == 409 and {p.record for p in server._clients[("runs/victim", "own")].values()} == {state(1)}


def test_quotas_are_checked_before_any_state_is_read(tmp_path, monkeypatch):
    """Through HTTP, the way requests take: a trainer beyond its quotas is refused before any of its
    states is parsed, and a list beyond the queue's before any is measured in tokens."""
    HeldStub.gate = threading.Event()
    server = make(tmp_path, lm=HeldStub(MODEL), max_sessions=1, max_queue=100)
    parsed, measured = [], []
    parse, measure = server.setup.parse_state, server.annotator.state_too_long
    monkeypatch.setattr(server.setup, "parse_state", lambda *a: parsed.append(1) or parse(*a))
    monkeypatch.setattr(server.annotator, "state_too_long", lambda *a: measured.append(1) or measure(*a))
    many = [(StateRecord("flood", (), f"{i}", ACTIONS), 1) for i in range(1000)]
    try:
        with running(server) as url:
            assert call(url + "/annotate", request([(state(0), 1)], client="engine"))[0] == 202
            wait_for(lambda: server.annotating == 1, 30, "the engine held")  # so the next list stays queued
            assert call(url + "/annotate", request([(state(1), 1)], client="flood", session="s0"))[0] == 202
            parsed.clear(), measured.clear()
            code, answer = call(url + "/annotate", request(many, client="flood", session="s1"))
            assert (code, "--max-sessions" in answer["error"], parsed, measured) == (429, True, [], [])
            code, answer = call(url + "/annotate", request(many, client="other"))
            assert (code, "--max-queue" in answer["error"], len(parsed), measured) == (503, True, 1000, [])
            HeldStub.gate.set()
    finally:
        HeldStub.gate.set()


def test_a_session_follows_its_trainer_to_another_peer_once_nothing_of_it_is_queued_or_waiting(tmp_path):
    """A dual-stack trainer falling back from IPv6 to IPv4: its session is refused from the new peer
    while its list is queued or a request of it waits, then goes on from there (and is tied to it)."""
    server = make(tmp_path)
    trainer, mine = ("runs/dual", "s"), {"client": "runs/dual", "session": "s"}
    server.submit(request([(state(1), 1)], **mine), peer=V6)

    async def waiting_from_v6() -> None:
        wait = asyncio.ensure_future(server.settled(trainer, 60, V6))
        await asyncio.sleep(0)  # its wait begun
        assert [p.record for p in server.next_batch()] == [state(1)]  # its list leaves the queue; the wait stays
        with pytest.raises(RequestError, match="a request waiting from another peer") as e:
            server.submit(request([(state(2), 1)], **mine), peer=V4)
        assert e.value.status == 409 and server.waiting == 1
        wait.cancel()

    with pytest.raises(RequestError, match="states queued or a request waiting from another peer"):
        server.submit(request([(state(2), 1)], **mine), peer=V4)
    asyncio.run(waiting_from_v6())
    assert server.submit(request([(state(2), 1)], **mine), peer=V4)["queued"] == 1  # nothing left from V6
    with pytest.raises(RequestError, match=f"another peer \\({re.escape(V4)}\\)"):  # tied to V4 now
        server.submit(request([], **mine), peer=V6)


def test_idle_connections_without_the_token_make_room_for_a_trainer(tmp_path):
    token = secrets.token_urlsafe(32)
    server = make(tmp_path, max_connections=3)
    with running(server, token=token) as url:
        port = int(url.rsplit(":", 1)[1])
        idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]  # never send a byte
        try:
            wait_for(lambda: server.connections == 3, 10, "the idle connections counted")
            assert call(url + "/annotate", request([(state(1), 1)]), token=token)[0] == 202  # not a 503
            idle[0].settimeout(10)
            assert idle[0].recv(1) == b""  # the longest idle one was closed
            assert stats(url, token)["connections_evicted"] >= 1
        finally:
            for s in idle:
                s.close()


# --- finding 8: the event loop free while a large request is checked ------------------------------------------


class HeldTokens(StubBackend):
    """The stub with a context, its first measure held until `go` is set (a large request's tokenizing
    that takes as long as a test needs)."""

    context_length = 10**6
    calls = 0
    go = threading.Event()

    def tokens_needed(self, prompt, candidates, max_new_tokens) -> int:
        HeldTokens.calls += 1
        assert HeldTokens.go.wait(120)  # longer than /stats is given to answer
        return 1


def test_stats_is_answered_while_a_large_request_is_measured(tmp_path):
    HeldTokens.calls, HeldTokens.go = 0, threading.Event()
    server = make(tmp_path, lm=HeldTokens(MODEL))
    many = [(StateRecord("go to the red ball", (), f"You see {i}", ACTIONS), 1) for i in range(200)]
    try:
        with running(server) as url:
            done: dict = {}
            big = threading.Thread(
                target=lambda: done.update(answer=call(url + "/annotate", request(many, client="big"))))
            big.start()
            wait_for(lambda: HeldTokens.calls > 0, 30, "the large request being measured")
            assert stats(url)["queue"] == 0 and HeldTokens.calls == 1  # answered while its first measure is held
            HeldTokens.go.set()
            big.join(60)
            assert done["answer"][0] == 202 and done["answer"][1]["queued"] == 200
    finally:
        HeldTokens.go.set()


# --- the memory bound (finding 2 through `illm serve` itself) ----------------------------------------------


@pytest.mark.slow  # 5 s quiet, more on a busy machine: a server process, 128 MB sent (the fast tier tests the mechanism)
def test_clients_that_leave_while_waiting_keep_the_servers_memory_within_its_bound(tmp_path):
    """serve.md's bound: a request's body is held while it is read and checked, one parsed at a time,
    and a waiting request holds its trainer's name only. Eight clients each post 16 MB (one state a
    thousand times over: one queued) with a long wait and leave: the server grows by at most the
    bodies serve.md states in all (the one being checked), and the second to the eighth add at most
    two (the allocator's high-water, not what they left)."""
    import os

    env = {**os.environ, "HF_HUB_OFFLINE": "1", "SLOW_S": "600"}
    env.pop("ILLM_SERVE_TOKEN", None)
    proc = subprocess.Popen([sys.executable, "-c", SLOW_SERVER, "serve", "--cache", str(tmp_path / "ann"), "--backend",
                             "slow", "--model", MODEL, "--history", "0", "--port", "0"],
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    try:
        found = re.search(r"http://127\.0\.0\.1:(\d+)", proc.stderr.readline())
        assert found
        url, port = f"http://127.0.0.1:{found.group(1)}", int(found.group(1))
        # holds the engine for the test
        assert call(url + "/annotate", request([(state(0), 1)], client="engine"))[0] == 202
        wait_for(lambda: stats(url)["annotating"] == 1, 30, "the engine busy")
        long = "go to the red ball and then " * 290  # 8,120 characters
        one = StateRecord(long, (), long, ACTIONS)
        limit = ServeLimits().max_request_bytes
        resident = [stats(url)["resident_mb"]]
        for n in range(8):
            body = json.dumps(request([(one, 1)] * 1000, client=f"gone-{n}", wait=120)).encode()
            assert 15 * 2**20 < len(body) <= limit
            sent = stats(url)["requests"]
            client = raw_post(port, body)
            del body
            wait_for(lambda: stats(url)["requests"] > sent, 60, "the request taken")
            client.close()
            wait_for(lambda: stats(url)["connections"] == 1, 30, "the client's connection released")
            resident.append(stats(url)["resident_mb"])
        assert resident[-1] - resident[0] <= stated_bodies() * limit / 2**20, resident
        assert resident[-1] - resident[1] <= 2 * limit / 2**20, resident  # nothing kept per client gone
        after = stats(url)
        assert after["clients"] == 8 and after["queue"] == 1 and after["waiting"] == 0  # one state, eight trainers
    finally:
        proc.kill()
        proc.communicate(timeout=30)


def stated_bodies() -> float:
    """docs/commands/serve.md's bound on what clients that leave while waiting grow the server by
    ("by **at most N × --max-request-mb** in all"), in request bodies."""
    from pathlib import Path

    page = (Path(__file__).parents[1] / "docs" / "commands" / "serve.md").read_text()
    found = re.search(r"by\s+\*\*at most ([\d.]+) × --max-request-mb\*\* in all", page)
    assert found, "docs/commands/serve.md states no bound for clients that leave while waiting"
    return float(found.group(1))
