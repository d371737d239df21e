"""`illm serve`: one model annotating the live requests of several `illm train --annotator URL`
runs. The scheduler merges the runs' missed states, highest summed visits first; malformed
requests get a 4xx and one line; a client that dies mid-request leaves nothing behind; two
trainers through one server fill one cache that verifies, with nothing stored twice."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.llm.spec import LLMSpec
from illm_tools.cache import AnnotationCache, verify
from illm_tools.keys import fingerprint_hash
from illm_tools.llm.stub import StubBackend
from illm_tools.serve import AnnotationServer, RequestError, record_to_json
from illm_tools.tasks.state import StateRecord

runner = CliRunner()
ENV = "BabyAI-GoToLocal-v0"
ACTIONS = ("turn left", "turn right", "go forward")
MODEL = "stub:16"
LLM = LLMSpec(backend="stub", model=MODEL, dtype="float32")
FINGERPRINT = fingerprint_hash(StubBackend(MODEL).fingerprint)


def state(i: int) -> StateRecord:
    return StateRecord("go to the red ball", (), f"You see a red ball {i} steps forward", ACTIONS)


def request(pending, client="run-a", **changes) -> dict:
    body = {"client": client, "model_fingerprint": FINGERPRINT, "env_id": ENV, "renderer": "babyai-text@1",
            "history_len": 0, "layout": "shared", "tasks": ["action", "summary"],
            "states": [{**record_to_json(s), "visits": n} for s, n in pending]}
    body.update(changes)
    return body


def test_the_scheduler_takes_the_most_visited_states_across_clients_once(tmp_path):
    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM, chunk=3)
    assert server.submit(request([(state(1), 5), (state(2), 1)], client="a"))["queued"] == 2
    assert server.submit(request([(state(2), 9), (state(3), 2), (state(4), 1)], client="b"))["queue"] == 4
    batch = server.next_batch()  # state 2: 1 + 9 visits from two runs, one entry
    assert [(p.record, p.visits, p.clients) for p in batch] == [(state(2), 10, {"a", "b"}), (state(1), 5, {"a"}),
                                                                (state(3), 2, {"b"})]
    assert server.queue_size() == 1
    assert server.submit(request([(state(7), 1)], client="b"))["queued"] == 1  # a newer list replaces b's
    assert [p.record for p in server.next_batch()] == [state(7)]
    assert server.submit(request([], client="a"))["queue"] == 0  # an empty list withdraws a client's states
    done, rows = server.annotate(batch)
    assert (done, rows) == (3, 6) and len(AnnotationCache(tmp_path / "ann")) == 6


@pytest.mark.parametrize("change,status,message", [
    ({"model_fingerprint": "0" * 64}, 409, "another model setup"),
    ({"tasks": ["action", "riddle"]}, 400, "unknown tasks riddle"),
    ({"history_len": -1}, 400, "history_len must be a whole number"),
    ({"layout": "fancy"}, 400, "layout must be one of"),
    ({"renderer": "hop@1:0:1.0:1"}, 400, "is not a hop renderer"),
    ({"states": [{"mission": "m"}]}, 400, "a state lacks history, observation, valid_actions"),
    ({"states": [{**record_to_json(state(1)), "visits": "many"}]}, 400, "visits must be"),
])
def test_malformed_requests_are_refused_with_their_reason(tmp_path, change, status, message):
    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM)
    with pytest.raises(RequestError, match=message) as e:
        server.submit(request([(state(1), 1)], **change))
    assert e.value.status == status and server.queue_size() == 0


@pytest.fixture
def served(tmp_path):
    """`illm serve` on the stub backend, on a free port, as a user starts it."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "cli.main", "serve", "--cache", str(tmp_path / "ann"), "--backend",
                             "stub", "--model", MODEL, "--port", "0", "--chunk", "8"],
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
    line = proc.stderr.readline()
    found = re.search(r"http://127\.0\.0\.1:(\d+)", line)
    assert found, line + proc.stderr.read()
    yield f"http://127.0.0.1:{found.group(1)}", proc
    if proc.poll() is None:
        proc.send_signal(2)
        proc.wait(30)


def call(url: str, body=None, raw: bytes | None = None) -> tuple[int, dict]:
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data=data, method="GET" if data is None else "POST"),
                                    timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_the_server_refuses_bad_requests_survives_a_dying_client_and_reports(served):
    url, proc = served
    assert call(url + "/annotate", raw=b"{not json")[0] == 400
    status, answer = call(url + "/annotate", {"client": "x"})
    assert status == 400 and answer["error"].startswith("the request lacks model_fingerprint")
    assert call(url + "/annotate", raw=b"[" + b" " * (17 * 2**20) + b"]")[0] == 413
    host, port = url.split("//")[1].split(":")
    with socket.create_connection((host, int(port))) as s:  # a client that dies mid-request
        s.sendall(b"POST /annotate HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 5000\r\n\r\n"
                  + json.dumps(request([(state(1), 3)]))[:200].encode())
    status, answer = call(url + "/annotate", request([(state(i), i) for i in range(1, 6)]))
    assert status == 202 and answer["queued"] == 5
    for _ in range(100):
        stats = call(url + "/stats")[1]
        if stats["annotated_states"] == 5:
            break
        time.sleep(0.1)
    assert stats["annotated_states"] == 5 and stats["rows"] == 10 and stats["queue"] == 0 and stats["refused"] == 3
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
              "--frames", "320", "--live-budget", "32", "--annotator", url]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
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
    assert all(n > 0 for n in landed)  # each run was told its states landed


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


def hop_states(n: int = 3):
    """Hop records of one env's first steps, as a hop trainer builds them (window 2)."""
    import numpy as np

    from illm_tools.hop.context import HopTracker

    tracker = HopTracker(1, 1, ACTIONS)
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        (record,) = tracker.records(["get to the green goal square"], [rng.integers(0, 9, (7, 7, 3), dtype=np.uint8)])
        out.append(record)
        tracker.push([2], [False])
    return out


def test_hop_states_travel_with_their_window_and_a_forged_one_is_refused(tmp_path):
    from illm_tools.hop.context import hop_renderer

    server = AnnotationServer(StubBackend(MODEL), AnnotationCache(tmp_path / "ann"), llm=LLM)
    records = hop_states()
    hop = {"renderer": hop_renderer(0, 1.0, 2), "history_len": 1, "env_id": "MiniGrid-MultiRoom-N6-v0"}
    body = request([(r, 1) for r in records], **hop)
    body = json.loads(json.dumps(body))  # as it travels
    assert server.submit(body)["queued"] == 3
    batch = server.next_batch()
    assert [p.record for p in batch] == records and all(len(p.record.frames) == len(r.frames)
                                                        for p, r in zip(batch, records))
    assert server.annotate(batch) == (3, 6)
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
