"""Issue 69, finding 11: what an OpenAI-compatible engine answers is checked as it will be stored
(float32: 1e39 is refused, never stored as inf), its echoed tokens must spell the prompt it was sent,
and a reply nested too deep, ragged embeddings or a text that is no string are one line naming the
engine. And the suspected one: what an `illm serve` server answers (`landed`, ...) never raises in
the trainer's client. Engines and servers are small fakes on 127.0.0.1, no model needed."""

from __future__ import annotations

import http.server
import json
import logging
import re
import threading

import pytest

from illm_tools.llm.backend import load_backend, resolve_model
from illm_tools.llm.openai_wire import EndpointError

WIDTH = 4
CONTEXT = "Valid actions: turn left, go forward. Action:"
CANDIDATES = [" turn left", " go forward"]


def _echo(prompt: str) -> dict:
    """An echo of `prompt` as vLLM gives it: word tokens whose texts spell it at their offsets, the first
    unscored, then one generated token."""
    tokens = re.findall(r"\s*\S+|\s+", prompt)
    offsets = [sum(len(t) for t in tokens[:i]) for i in range(len(tokens))]
    return {"text": prompt + " x", "finish_reason": "length",
            "logprobs": {"tokens": tokens + [" x"], "token_logprobs": [None] + [-1.0] * (len(tokens) - 1) + [-1.0],
                         "text_offset": offsets + [len(prompt)]}}


class Engine:
    """/v1/models, /version, /v1/completions (echo, one greedy token with its top log-probs, or a text)
    and /v1/embeddings of width `WIDTH`; `ranking`, `texts` and `embeddings` rewrite an answer (a
    function of the answer: a dict, bytes sent as the body, or ("raw", bytes) sent with no status line)
    once the backend has connected."""

    def __init__(self):
        self.ranking = self.texts = self.embeddings = None
        engine = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                self._send({"data": [{"id": "m"}]} if self.path == "/v1/models" else {"version": "fake-1"})

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                self._send(engine.answer(self.path, body))

            def _send(self, answer):
                if isinstance(answer, tuple):  # ("raw", bytes): no HTTP at all
                    self.wfile.write(answer[1])
                    return
                raw = answer if isinstance(answer, bytes) else json.dumps(answer).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(raw)))
                self.end_headers()
                self.wfile.write(raw)

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        threading.Thread(target=self.server.serve_forever, args=(0.02,), daemon=True).start()
        self.url = f"http://127.0.0.1:{self.server.server_port}/v1"

    def answer(self, path: str, body: dict):
        if path == "/v1/embeddings":
            answer = {"data": [{"index": i, "embedding": [0.5] * WIDTH} for i in range(len(body["input"]))]}
            return self.embeddings(answer) if self.embeddings else answer
        prompts = body["prompt"] if isinstance(body["prompt"], list) else [body["prompt"]]
        if body.get("echo"):
            answer = {"choices": [{**_echo(p), "index": i} for i, p in enumerate(prompts)]}
            return self.ranking(answer) if self.ranking and len(prompts) > 1 else answer
        if body.get("logprobs") and body["max_tokens"] == 1:  # the probe's greedy token: " six" after any context
            return {"choices": [{"index": i, "text": " six", "logprobs": {
                "tokens": [" six"], "token_logprobs": [-1.0], "text_offset": [len(p)],
                "top_logprobs": [{" six": -1.0}]}} for i, p in enumerate(prompts)]}
        answer = {"choices": [{"index": i, "text": " a red ball", "finish_reason": "stop",
                               "logprobs": {"tokens": [" a", " red", " ball"]}} for i in range(len(prompts))]}
        return self.texts(answer) if self.texts else answer

    def stop(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def engine():
    e = Engine()
    yield e, load_backend("openai", resolve_model("openai", "m", endpoint=e.url))
    e.stop()


def test_the_fake_engine_ranks_and_embeds(engine):
    """The control: the fake's honest answers pass every check (what the refusals below change)."""
    fake, remote = engine
    assert remote.engine.aligned and remote.hidden_size == WIDTH
    scores = remote.score([CONTEXT], [CANDIDATES])[0]
    assert scores.token_logprobs == [[-1.0, -1.0], [-1.0, -1.0]]
    assert remote.embed(["a", "b"]).shape == (2, WIDTH)
    assert [g.text for g in remote.generate(["go"])] == [" a red ball"]


def _overflowing_logprob(answer):
    answer["choices"][0]["logprobs"]["token_logprobs"][-2] = -1e39  # finite in float64, -inf in float32
    return answer


def _overflowing_sum(answer):
    for i in (-2, -3):
        answer["choices"][0]["logprobs"]["token_logprobs"][i] = -3e38  # each finite in float32, the sum not
    return answer


def _other_tokens(answer):
    lp = answer["choices"][1]["logprobs"]  # the echo of another text at the same offsets
    lp["tokens"] = [t.upper() for t in lp["tokens"]]
    return answer


def _no_tokens(answer):
    del answer["choices"][0]["logprobs"]["tokens"]
    return answer


def _shifted_offsets(answer):
    lp = answer["choices"][0]["logprobs"]  # the texts spell the prompt, the offsets say otherwise
    lp["text_offset"] = [o + 1 for o in lp["text_offset"]]
    return answer


def _logprobs_list(answer):
    answer["choices"][0]["logprobs"] = [1, 2]
    return answer


def _deep(answer):
    return b"[" * 100_000 + b"]" * 100_000


@pytest.mark.parametrize("mutate,said", [
    (_overflowing_logprob, "not all finite numbers at most 0 (in float32"),
    (_overflowing_sum, "not all finite numbers at most 0 (in float32"),
    (_other_tokens, "echoed tokens that do not spell the prompt it was sent"),
    (_no_tokens, "echoed tokens that do not spell the prompt it was sent"),
    (_shifted_offsets, "echoed tokens that do not spell the prompt it was sent"),
    (_logprobs_list, "log-probabilities that are not a JSON object"),
    (_deep, "answered JSON nested too deep to read")])
def test_a_ranking_is_checked_as_it_is_stored_and_against_the_prompt_sent(engine, mutate, said):
    fake, remote = engine
    fake.ranking = mutate
    with pytest.raises(EndpointError, match=re.escape(said)) as e:
        remote.score([CONTEXT], [CANDIDATES])
    assert fake.url in str(e.value) and len(str(e.value).splitlines()) == 1


def _ragged(answer):
    answer["data"][1]["embedding"] = answer["data"][1]["embedding"][:-1]
    return answer


def _overflowing_embedding(answer):
    answer["data"][0]["embedding"][0] = 1e39
    return answer


def _strings(answer):
    answer["data"][0]["embedding"] = ["0.5"] * WIDTH  # numpy would read them as numbers
    return answer


def _index_strings(answer):
    answer["data"][0]["index"] = "0"
    return answer


@pytest.mark.parametrize("mutate,said", [
    (_ragged, "not finite vectors of 4 dimensions"), (_overflowing_embedding, "finite in float32"),
    (_strings, "not finite vectors of 4 dimensions"), (_index_strings, "each index once is expected"),
    (_deep, "answered JSON nested too deep to read")])
def test_embeddings_are_checked_as_they_are_stored(engine, mutate, said):
    fake, remote = engine
    fake.embeddings = mutate
    with pytest.raises(EndpointError, match=re.escape(said)) as e:
        remote.embed(["a", "b"])
    assert fake.url in str(e.value) and len(str(e.value).splitlines()) == 1


def test_an_answer_that_is_not_http_is_retried_then_one_line(engine):
    fake, remote = engine
    fake.embeddings = lambda answer: ("raw", b"garbage\r\n\r\n")
    remote.embed_client.backoff = 0.0  # the retries' pauses, shortened
    with pytest.raises(EndpointError, match="failed 5 times") as e:
        remote.embed(["a"])
    assert fake.url in str(e.value) and len(str(e.value).splitlines()) == 1


def test_a_generated_text_that_is_no_string_is_refused(engine):
    fake, remote = engine
    fake.texts = lambda answer: {"choices": [{**c, "text": ["a"]} for c in answer["choices"]]}
    with pytest.raises(EndpointError, match="completion whose text is not a string") as e:
        remote.generate(["go"])
    assert fake.url in str(e.value)


# --- the trainer's client of an `illm serve` server -------------------------------------------------------
def _illm_server(post, limits=None):
    """A fake `illm serve` of the stub's setup: GET /stats answers `limits`, POST runs `post(handler)`."""
    from fakes import STUB_LLM, QuietHandler
    from illm_tools.annotate.wire import PROTOCOL

    stats = json.dumps({"protocol": PROTOCOL, "model_fingerprint": STUB_LLM.fingerprint(),
                        "limits": {"max_states": 64} if limits is None else limits}).encode()

    class Server(QuietHandler):
        def do_GET(self):
            self.reply(200, stats)

        def do_POST(self):
            self.rfile.read(int(self.headers["Content-Length"]))
            post(self)

    return Server


def _client(url, **kw):
    from fakes import STUB_LLM
    from illm_tools.rl.live_remote import RemoteLive
    from illm_tools.tasks.annotation_setup import AnnotationSetup

    return RemoteLive(url, client="run", llm=STUB_LLM, budget=8,
                      setup=AnnotationSetup("BabyAI-GoToLocal-v0", "babyai-text@1", history_len=0), **kw)


@pytest.mark.parametrize("reply", [b'{"landed": "x"}', b'{"landed": 1e400}', b'{"landed": [1]}', b'{"landed": -5}',
                                   b'{"queued": null}', b'{"failed": "many"}', b"[" * 100_000 + b"]" * 100_000,
                                   None])  # None: a status line of garbage, no HTTP at all
def test_a_hostile_servers_counts_never_raise_in_the_trainer(reply, caplog):
    from fakes import http_fake, serve_state

    def post(handler):
        if reply is None:
            handler.wfile.write(b"garbage\r\n\r\n")
        else:
            handler.reply(202, reply)

    with http_fake(_illm_server(post)) as url, caplog.at_level(logging.WARNING, logger="illm_tools.rl.live"):
        live = _client(url, wait=1.0)
        assert live.submit([serve_state(0)]) == 0  # sync mode: the trainer's own call
        assert (live.counts["refused"], live.counts["accepted"], live.stats()) == (1, 0, {"live_queue": 0.0})
        assert any("not an illm server's answer" in r.getMessage() for r in caplog.records)
        live.close(timeout=0.5)


def test_a_server_that_closes_without_answering_is_down_not_hostile(caplog):
    """A connection closed with no answer (a server being killed: RemoteDisconnected, which is an
    http.client exception too) is a server that does not answer, tried again later, not a bad answer."""
    from fakes import http_fake, serve_state

    def post(handler):
        handler.close_connection = True  # nothing written: the client sees the connection closed

    with http_fake(_illm_server(post)) as url, caplog.at_level(logging.WARNING, logger="illm_tools.rl.live"):
        live = _client(url, wait=1.0)
        assert live.submit([serve_state(0)]) == 0
        said = [r.getMessage() for r in caplog.records]
        assert sum("does not answer" in m for m in said) == 1 and not any("not HTTP" in m for m in said), said
        live.close(timeout=0.5)


@pytest.mark.parametrize("limits", [{"max_states": "x"}, [1, 2], {"max_states": 1e400}])
def test_a_servers_limits_that_are_no_counts_are_one_line_at_start(limits):
    from fakes import http_fake
    from illm_tools.errors import UsageError

    with http_fake(_illm_server(lambda handler: None, limits)) as url:
        with pytest.raises(UsageError, match="max_states .* not a count") as e:
            _client(url)
        assert len(str(e.value).splitlines()) == 1
