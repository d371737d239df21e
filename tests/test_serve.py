"""`illm serve`: one model annotating the live requests of several `illm train --annotator URL`
runs. The scheduler merges the runs' missed states, highest summed visits first; malformed
requests get a 4xx and one line; a client that dies mid-request leaves nothing behind; two
trainers through one server fill one cache that verifies, with nothing stored twice. For a
cluster: a token on every request (and required beyond loopback), limits answered with 413/503
and Retry-After, a trainer's pending list its own, a stalled client cut off, SIGTERM finishing the
batch in progress, and a trainer that survives its server killed and restarted.

One module a little past 400 lines: its server fixtures (`served`, `start_server`) are shared by every
test of one server's life, from a request to a restart (the limits' own tests: test_serve_hardening.py)."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.cache import AnnotationCache, verify
from illm_tools.llm.stub import StubBackend
from illm_tools.serve import AnnotationServer, RequestError, ServeConfig, ServeLimits, record_to_json
from illm_tools.tasks.prompt_config import PromptConfig
from fakes import STUB_LLM as LLM, STUB_MODEL as MODEL
from fakes import SLOW_SERVER, call, hop_states, serve_request as request, serve_state as state, wait_for

runner = CliRunner()
ENV = "BabyAI-GoToLocal-v0"
TOKEN = "Jq3vX9tKp2Lw7RzN5mYc8HbD4fGs6AeU"  # 32 characters of 62: about 190 bits
ENV_OFFLINE = {**os.environ, "HF_HUB_OFFLINE": "1"}
ENV_OFFLINE.pop("ILLM_SERVE_TOKEN", None)


def test_the_scheduler_takes_the_most_visited_states_across_clients_once(tmp_path):
    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM, prompt=PromptConfig(history_len=0), chunk=3)
    assert server.submit(request([(state(1), 5), (state(2), 1)], client="a"))["queued"] == 2
    assert server.submit(request([(state(2), 9), (state(3), 2), (state(4), 1)], client="b"))["queue"] == 4
    batch = server.next_batch()  # round-robin: a's most visited, b's, then a's next (state 2, b's too) is taken
    a, b = ("a", "s1"), ("b", "s1")
    assert [(p.record, p.clients) for p in batch] == [(state(1), {a}), (state(2), {a, b}), (state(3), {b})]
    assert server.queue_size() == 1
    assert server.submit(request([(state(7), 1)], client="b"))["queued"] == 1  # a newer list replaces b's
    assert [p.record for p in server.next_batch()] == [state(7)]
    assert server.submit(request([], client="a"))["queue"] == 0  # an empty list withdraws a client's states
    done, rows, failed = server.annotate(batch)
    assert (done, rows, failed) == (3, 6, []) and len(AnnotationCache(tmp_path / "ann")) == 6


@pytest.mark.parametrize("change,status,message", [
    ({"model_fingerprint": "0" * 64}, 409, "another model setup"),
    ({"tasks": ["action", "riddle"]}, 409, "the request reads riddle too"),
    ({"history_len": -1}, 400, "history_len must be a whole number"),
    ({"tasks": 5}, 400, "tasks must be a list"),
    ({"layout": "fancy"}, 409, "--layout shared"),
    ({"renderer": "hop@1:0:1.0:1"}, 409, "renderer hop@"),
    ({"states": [{"mission": "m"}]}, 400, "a state lacks history, observation, valid_actions"),
    ({"states": [{**record_to_json(state(1)), "visits": "many"}]}, 400, "visits must be"),
])
def test_malformed_requests_are_refused_with_their_reason(tmp_path, change, status, message):
    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM, prompt=PromptConfig(history_len=0))
    with pytest.raises(RequestError, match=message) as e:
        server.submit(request([(state(1), 1)], **change))
    assert e.value.status == status and server.queue_size() == 0


@pytest.fixture
def start_server(tmp_path):
    """Start `illm serve` on the stub backend (`slow`: batches that take `slow` seconds each) as a
    user starts it, on a free port (or `port`); every server started is stopped at the end."""
    procs = []

    def start(*extra, env=None, port=0, slow: float = 0.0):
        env = {**ENV_OFFLINE, **(env or {}), **({"SLOW_S": str(slow)} if slow else {})}
        head = [sys.executable, "-c", SLOW_SERVER] if slow else [sys.executable, "-m", "cli.main"]
        proc = subprocess.Popen([*head, "serve", "--cache", str(tmp_path / "ann"), "--backend",
                                 "slow" if slow else "stub", "--model", MODEL, "--history", "0", "--port", str(port),
                                 "--chunk", "8",
                                 *map(str, extra)], stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        procs.append(proc)
        line = proc.stderr.readline()
        found = re.search(r"http://127\.0\.0\.1:(\d+)", line)
        assert found, line + proc.stderr.read()
        return f"http://127.0.0.1:{found.group(1)}", proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)


@pytest.fixture
def served(start_server):
    """`illm serve` on the stub backend, on a free port, as a user starts it."""
    url, proc = start_server()
    yield url, proc
    if proc.poll() is None:
        proc.send_signal(2)
        proc.wait(30)


def test_the_server_refuses_bad_requests_survives_a_dying_client_and_reports(served):
    url, proc = served
    assert call(url + "/annotate", raw=b"{not json")[0] == 400
    status, answer = call(url + "/annotate", {"client": "x"})
    assert status == 400 and answer["error"].startswith("the request lacks session, model_fingerprint, states")
    assert call(url + "/annotate", raw=b"[" + b" " * (17 * 2**20) + b"]")[0] == 413
    host, port = url.split("//")[1].split(":")
    with socket.create_connection((host, int(port))) as s:  # a client that dies mid-request
        s.sendall(f"POST /annotate HTTP/1.1\r\nHost: {host}:{port}\r\n".encode() + b"Content-Type: application/json\r\nContent-Length: 5000\r\n\r\n"
                  + json.dumps(request([(state(1), 3)]))[:200].encode())
    status, answer = call(url + "/annotate", request([(state(i), i) for i in range(1, 6)]))
    assert status == 202 and answer["queued"] == 5
    for _ in range(100):
        stats = call(url + "/stats")[1]
        if stats["annotated_states"] == 5:
            break
        time.sleep(0.1)
    assert stats["annotated_states"] == 5 and stats["rows"] == 10 and stats["queue"] == 0 and stats["refused"] == 3
    assert stats["resident_mb"] > 0 and stats["limits"] == dataclasses.asdict(ServeLimits())
    assert call(url + "/annotate", request([], client="run-a"))[1]["landed"] == 5
    proc.send_signal(2)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0 and "5 states annotated (10 rows)" in out and "Traceback" not in err


@pytest.mark.slow  # 10 s: the fast tier's time is spent
def test_two_trainers_share_one_server_and_one_cache(tmp_path, served):
    url, _ = served
    ann = tmp_path / "ann"
    common = [sys.executable, "-m", "cli.main", "train", "--env", ENV, "--method", "illm", "--cache", str(ann),
              "--backend", "stub", "--model", MODEL, "--history", "0", "--num-envs", "2", "--num-steps", "32",
              "--frames", "320", "--live-budget", "32", "--live-mode", "sync", "--annotator", url]
    env = ENV_OFFLINE
    runs = [subprocess.Popen([*common, "--seed", str(i), "--out", str(tmp_path / f"run{i}")], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    for proc in runs:
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-2000:]
    stats = call(url + "/stats")[1]
    assert stats["annotated_states"] > 0 and stats["errors"] == 0
    report = verify(ann)
    assert report.ok and report.rows == len(AnnotationCache(ann))  # nothing stored twice
    landed = [sum(json.loads(line).get("charts/live_annotations", 0) for line in
                  (tmp_path / f"run{i}" / "metrics.jsonl").read_text().splitlines()) for i in range(2)]
    assert all(n > 0 for n in landed)  # each run was told its states landed (sync: in the rollout that sent them)


def test_a_request_that_waits_is_answered_once_its_states_have_landed(start_server):
    url, _ = start_server(slow=0.5)  # each batch of 8 takes half a second: without the wait, nothing lands in time
    pending = [(state(i), 1) for i in range(1, 13)]  # two batches
    status, answer = call(url + "/annotate", request(pending, wait=30))
    assert status == 202 and answer["queued"] == 12 and answer["landed"] == 12 and not answer["pending"]
    status, answer = call(url + "/annotate", request(pending[:2], client="run-b", wait=0))  # no wait: at once
    assert status == 202 and answer["landed"] == 0
    for wrong in (-1, 1e9, "10", True, None):
        status, answer = call(url + "/annotate", json.loads(json.dumps(request(pending, wait=wrong))))
        assert status == 400 and answer["error"].startswith("wait must be a number of seconds"), (wrong, answer)


def test_a_trainer_without_its_server_is_refused_in_one_line(tmp_path):
    out = runner.invoke(app, ["train", "--env", ENV, "--method", "illm", "--cache", str(tmp_path / "ann"),
                              "--backend", "stub", "--model", MODEL, "--history", "0", "--num-envs", "2",
                              "--num-steps", "16", "--frames", "32", "--annotator", "http://127.0.0.1:9",
                              "--out", str(tmp_path / "run")])
    assert out.exit_code == 1 and "no illm server answers at http://127.0.0.1:9" in out.output
    assert not (tmp_path / "run").exists()  # refused before it wrote anything: no folder holding only its lock
    assert len(out.output.strip().splitlines()) == 1


def test_a_trainer_of_another_model_setup_is_refused_by_the_server_in_one_line(tmp_path, served):
    url, _ = served
    out = runner.invoke(app, ["train", "--env", ENV, "--method", "illm", "--cache", str(tmp_path / "ann"),
                              "--backend", "stub", "--model", "stub:24", "--history", "0", "--num-envs", "2",
                              "--num-steps", "16", "--frames", "32", "--annotator", url, "--out", str(tmp_path / "r")])
    assert out.exit_code == 1 and "annotates with --backend stub --model stub:16 --dtype float32 --quant none, another model setup than this run's --backend stub --model stub:24" in out.output
    assert len(out.output.strip().splitlines()) == 1


def test_hop_states_travel_with_their_window_and_a_forged_one_is_refused(tmp_path):
    from illm_tools.tasks.annotation_setup import hop_renderer

    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM, prompt=PromptConfig(history_len=1))
    records = hop_states()
    hop = {"renderer": hop_renderer(0, 100.0, 2), "history_len": 1, "env_id": "MiniGrid-MultiRoom-N6-v0"}
    body = request([(r, 1) for r in records], **hop)
    body = json.loads(json.dumps(body))  # as it travels
    assert server.submit(body)["queued"] == 3
    batch = server.next_batch()
    assert [p.record for p in batch] == records and all(len(p.record.frames) == len(r.frames)
                                                        for p, r in zip(batch, records))
    assert server.annotate(batch) == (3, 6, [])
    forged = json.loads(json.dumps(request([(records[1], 1)], **hop)))
    forged["states"][0]["prev_actions"][-1] = 0  # not the action the history says was taken
    with pytest.raises(RequestError, match="does not match its content name"):
        server.submit(forged)
    with pytest.raises(RequestError, match="needs frames and prev_actions"):
        server.submit(request([(state(1), 1)], **hop))


@pytest.mark.slow  # 8 s
def test_a_hop_run_annotates_through_the_server(tmp_path, served):
    url, _ = served
    out = runner.invoke(app, ["train", "--env", "MiniGrid-MultiRoom-N6-v0", "--mode", "hop", "--method", "illm",
                              "--cache", str(tmp_path / "ann"), "--backend", "stub", "--model", MODEL, "--history", "0",
                              "--num-envs", "2", "--num-steps", "16", "--frames", "96", "--live-budget", "8",
                              "--annotator", url, "--out", str(tmp_path / "run")])
    assert out.exit_code == 0, out.output
    for _ in range(100):
        stats = call(url + "/stats")[1]
        if stats["annotated_states"] and not stats["queue"]:
            break
        time.sleep(0.1)
    assert stats["annotated_states"] > 0 and stats["errors"] == 0 and stats["refused"] == 0


# --- a server for a cluster: access, limits, faults -------------------------------------------------------


def test_a_trainer_cannot_replace_or_withdraw_another_trainers_list(tmp_path):
    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM, prompt=PromptConfig(history_len=0), chunk=8)
    server.submit(request([(state(1), 1), (state(2), 1)], client="runs/a", session="first"))
    # the same client name from another trainer (a stranger, a resumed copy of the run): a list of its own
    assert server.submit(request([(state(3), 1)], client="runs/a", session="other"))["queue"] == 3
    assert server.submit(request([], client="runs/a", session="other"))["queue"] == 2  # withdraws its own only
    assert {p.record for p in server.next_batch()} == {state(1), state(2)}


def test_limits_answer_413_and_503_with_retry_after_as_documented(tmp_path):
    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM, prompt=PromptConfig(history_len=0),
                              limits=ServeLimits(max_clients=2, max_states=3, max_queue=4, max_client_share=1.0,
                                                 max_peer_share=1.0))
    with pytest.raises(RequestError, match=r"at most 3 states \(the server's --max-states\), this one 4") as e:
        server.submit(request([(state(i), 1) for i in range(4)]))
    assert e.value.status == 413
    server.submit(request([(state(1), 1), (state(2), 1), (state(3), 1)], client="a"))
    with pytest.raises(RequestError, match="beyond the server's --max-queue 4") as e:
        server.submit(request([(state(4), 1), (state(5), 1)], client="b"))
    assert e.value.status == 503 and 1 <= e.value.retry_after <= 60
    assert server.queue_size() == 3  # nothing of the refused request queued, a's list kept
    server.submit(request([(state(3), 1), (state(4), 1)], client="b"))  # one state shared with a's: 4 in all
    assert server.submit(request([(state(1), 1), (state(2), 1), (state(4), 1)], client="a"))["queue"] == 4  # its own replaced
    with pytest.raises(RequestError, match="states of 2 trainers, its limit") as e:
        server.submit(request([(state(1), 1)], client="c"))
    assert e.value.status == 503


def test_a_non_loopback_listen_needs_a_token(tmp_path, monkeypatch):
    monkeypatch.delenv("ILLM_SERVE_TOKEN", raising=False)
    for host in ("0.0.0.0", "::", ""):
        out = runner.invoke(app, ["serve", "--cache", str(tmp_path / "ann"), "--backend", "stub", "--host", host])
        assert out.exit_code == 1 and "listens beyond this machine" in out.output and "--token" in out.output
        assert len(out.output.strip().splitlines()) == 1
    assert ServeConfig(host="localhost").token is None and ServeConfig(host="::1").token is None
    assert ServeConfig(host="0.0.0.0", token=TOKEN).token == TOKEN
    assert TOKEN not in repr(ServeConfig(host="0.0.0.0", token=TOKEN))
    monkeypatch.setenv("ILLM_SERVE_TOKEN", TOKEN)
    assert ServeConfig(host="0.0.0.0").token == TOKEN  # from the environment
    out = runner.invoke(app, ["serve", "--cache", str(tmp_path / "ann"), "--backend", "stub", "--token", "tooshort-xyz"])
    assert out.exit_code == 1 and "at least 16 printable characters" in out.output and "tooshort" not in out.output
    out = runner.invoke(app, ["serve", "--cache", str(tmp_path / "ann"), "--backend", "stub", "--token", "a" * 40])
    assert out.exit_code == 1 and "fewer than the 128 a server's token needs" in out.output
    assert "secrets.token_urlsafe(32)" in out.output and "a" * 40 not in out.output
    assert len(out.output.strip().splitlines()) == 1


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_the_token_is_required_on_every_request(tmp_path, start_server):
    url, proc = start_server("--max-queue", 2, "--max-client-share", 1, env={"ILLM_SERVE_TOKEN": TOKEN})
    for body in (None, request([(state(1), 1)])):
        for token in (None, "wrong-token-0123456789"):
            status, answer = call(url + ("/stats" if body is None else "/annotate"), body, token=token)
            assert status == 401 and "pass the server's token with --annotator-token" in answer["error"]
    status, stats = call(url + "/stats", token=TOKEN)
    assert status == 200 and stats["unauthorized"] == 4 and stats["queue"] == 0
    headers = {}
    status, answer = call(url + "/annotate", request([(state(i), 1) for i in range(3)]), token=TOKEN, answer_headers=headers)
    assert status == 503 and int(headers["Retry-After"]) >= 1 and "--max-queue 2" in answer["error"]
    out = runner.invoke(app, ["train", "--env", ENV, "--method", "illm", "--cache", str(tmp_path / "ann"),
                              "--backend", "stub", "--model", MODEL, "--history", "0", "--num-envs", "2",
                              "--num-steps", "16", "--frames", "32", "--annotator", url, "--out", str(tmp_path / "r")],
                        env={"ILLM_SERVE_TOKEN": ""})
    assert out.exit_code == 1 and "needs a token and this run has none: pass the server's token with " \
                                  "--annotator-token" in out.output
    assert len(out.output.strip().splitlines()) == 1
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert TOKEN not in out + err  # never printed


def test_an_annotator_token_without_an_annotator_is_refused_in_one_line(tmp_path):
    out = runner.invoke(app, ["train", "--env", ENV, "--method", "illm", "--cache", str(tmp_path / "ann"),
                              "--backend", "stub", "--model", MODEL, "--history", "0", "--frames", "32",
                              "--annotator-token", TOKEN, "--out", str(tmp_path / "r")])
    assert out.exit_code == 1 and "give --annotator URL too" in out.output and TOKEN not in out.output
    assert len(out.output.strip().splitlines()) == 1 and not (tmp_path / "r").exists()


def test_a_stalled_client_is_cut_off_and_holds_no_worker(start_server):
    url, _ = start_server("--request-timeout", 1)
    host, port = url.split("//")[1].split(":")
    body = json.dumps(request([(state(1), 3)])).encode()
    with socket.create_connection((host, int(port))) as stalled, socket.create_connection((host, int(port))) as idle:
        stalled.sendall(f"POST /annotate HTTP/1.1\r\nHost: {host}:{port}\r\n".encode() + b"Content-Type: application/json\r\n"
                        + f"Content-Length: {len(body)}\r\n\r\n".encode() + body[:50])
        assert call(url + "/annotate", request([(state(2), 1)], client="b"))[0] == 202  # served meanwhile
        wait_for(lambda: call(url + "/stats")[1]["annotated_states"] == 1, 30, "the other client's state annotated")
        stalled.settimeout(10)
        answer = stalled.recv(4096).decode()
        assert answer.startswith("HTTP/1.1 408") and "not sent whole within 1 s" in answer  # recv's timeout bounds it
        idle.settimeout(10)
        assert idle.recv(1) == b""  # an idle connection is closed too
    stats = call(url + "/stats")[1]
    assert stats["timeouts"] == 1 and stats["queue"] == 0


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_sigterm_finishes_the_batch_in_progress_and_writes_it(tmp_path, start_server):
    url, proc = start_server(slow=1.0)
    assert call(url + "/annotate", request([(state(i), 1) for i in range(4)]))[0] == 202
    wait_for(lambda: call(url + "/stats")[1]["annotating"] == 4, 30, "the batch started")
    proc.send_signal(signal.SIGTERM)
    status, answer = wait_for(lambda: (lambda r: r if r[0] == 503 else None)(
        call(url + "/annotate", request([(state(9), 1)], client="late"))), 10, "refused while stopping")
    assert "the server is stopping" in answer["error"]
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "SIGTERM: finishing the batch in progress" in err and "Traceback" not in err
    assert "4 states annotated (8 rows)" in out
    report = verify(tmp_path / "ann")
    assert report.ok and report.rows == 8 == len(AnnotationCache(tmp_path / "ann"))


def test_sigterm_exits_within_the_batch_deadline_when_the_engine_is_stuck(tmp_path, start_server):
    url, proc = start_server("--batch-deadline", 2, slow=600.0)  # a batch that would take 10 minutes
    assert call(url + "/annotate", request([(state(i), 1) for i in range(2)]))[0] == 202
    wait_for(lambda: call(url + "/stats")[1]["annotating"] == 2, 30, "the batch started")
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)  # well before the batch would end: the deadline cut the wait
    assert proc.returncode == 0 and "past its deadline" in err and "Traceback" not in err, err[-2000:]
    assert "0 states annotated" in out


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_a_remote_trainer_backs_off_a_full_server_and_says_so_once(tmp_path, start_server, caplog):
    from illm_tools.rl.live_remote import RemoteLive
    from illm_tools.tasks.annotation_setup import AnnotationSetup

    url, _ = start_server("--max-queue", 2, env={"ILLM_SERVE_TOKEN": TOKEN})
    setup = AnnotationSetup(ENV, "babyai-text@1", history_len=0)
    live = RemoteLive(url, client="run", llm=LLM, setup=setup, budget=8, token=TOKEN)
    with caplog.at_level(logging.WARNING, logger="illm_tools.rl.live"):
        assert live.submit([state(i) for i in range(3)], [1, 1, 1]) == 0  # more states than the queue holds
        wait_for(lambda: live.counts["busy"] == 1, 30, "the server's 503")
        for _ in range(4):  # the next rollouts, within the Retry-After (5 s: no throughput measured yet)
            assert live.submit([state(i) for i in range(3)], [1, 1, 1]) == 0
            time.sleep(0.2)
    assert live.counts["sent"] == 1 and not live.idle  # it waits out the Retry-After, the newest list kept
    assert sum("is full" in r.getMessage() for r in caplog.records) == 1
    live.close()


@pytest.mark.slow  # 15 s on a quiet machine, 40 s on a busy one
def test_a_trainer_survives_its_server_killed_and_restarted(tmp_path, start_server):
    url, first = start_server(env={"ILLM_SERVE_TOKEN": TOKEN})
    port = int(url.rsplit(":", 1)[1])
    ann = tmp_path / "ann"
    trainer = subprocess.Popen(
        [sys.executable, "-m", "cli.main", "train", "--env", ENV, "--method", "illm", "--cache", str(ann),
         "--backend", "stub", "--model", MODEL, "--history", "0", "--num-envs", "2", "--num-steps", "16",
         "--frames", "64000", "--live-budget", "8", "--annotator", url, "--annotator-token", TOKEN,
         "--no-tensorboard", "--out", str(tmp_path / "run")],
        env=ENV_OFFLINE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: call(url + "/stats", token=TOKEN)[1]["annotated_states"] >= 8, 120, "states annotated")
        first.kill()  # no goodbye: its queue and the batch in progress are gone
        first.communicate(timeout=30)
        time.sleep(2.0)  # the trainer meets a dead server (and says so once)
        assert trainer.poll() is None
        rows_before = len(AnnotationCache(ann))
        url2, second = start_server(port=port, env={"ILLM_SERVE_TOKEN": TOKEN})
        assert url2 == url
        wait_for(lambda: call(url + "/stats", token=TOKEN)[1]["annotated_states"] >= 8, 120,
                 "the trainer's states landing after the restart")
        assert len(AnnotationCache(ann)) > rows_before
    finally:
        trainer.send_signal(signal.SIGINT)  # stop after the update in progress
        out, err = trainer.communicate(timeout=120)
    assert trainer.returncode == 130 and "stopped at" in out, err[-2000:]
    assert err.count("does not answer") == 1 and err.count("answers again") == 1, err[-2000:]
    assert TOKEN not in out + err + (tmp_path / "run" / "config.json").read_text()
    report = verify(ann)
    assert report.ok and report.rows == len(AnnotationCache(ann))  # nothing annotated twice
    tasks = AnnotationCache(ann).tasks()
    assert tasks["action"] == tasks["summary"] > 8
