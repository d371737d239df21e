"""The openai backend against a small OpenAI-compatible server started here, which answers from the
transformers backend on a tiny model (as vLLM would from its own): the same scores and summaries as
the transformers backend on the same states, the same keys' setup apart from the model's identity,
retries on 429/5xx, one line and nothing written when the server keeps failing."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import socket
import threading

import numpy as np
import pytest
import torch

from illm_tools.annotate.engine import Annotator
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.llm.backend import load_backend, resolve_model
from illm_tools.llm.openai import OpenAIBackend
from illm_tools.llm.openai_wire import EndpointError
from illm_tools.llm.transformers_backend import TransformersBackend
from illm_tools.tasks.state import StateRecord
from fakes import trains_with_the_engine_stopped

pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")
ACTIONS = ("turn left", "turn right", "go forward")


class Server:
    """/v1/models, /version, /v1/completions (echo + logprobs, or greedy completion) and
    /v1/embeddings, answered by `lm` (a LoadedModel); `fail` answers that many requests with 503.
    As engines that differ: `single` answers a list of prompts with 500 (llama-cpp-python's server),
    `shifted` scores each echoed token with the logits at its own position instead of the previous
    one (its echo), `no_echo` gives no prompt log-probs."""

    def __init__(self, lm, name: str = "tiny", *, single: bool = False, shifted: bool = False, no_echo: bool = False,
                 root: str | None = None):
        from aiohttp import web

        self.lm, self.name, self.fail, self.requests = lm, name, 0, 0
        self.status, self.drop = 503, False  # how a failing request fails: this status, or the connection cut
        self.single, self.shifted, self.no_echo = single, shifted, no_echo
        self.mutate = self.mutate_embeddings = None  # an answer rewritten before it is sent (a misbehaving engine)
        self.backend = TransformersBackend(lm)
        app = web.Application()
        served = {"id": self.name, **({"root": root} if root else {})}  # vLLM's `root`: the weights it serves
        app.router.add_get("/v1/models", lambda r: web.json_response({"data": [served]}))
        app.router.add_get("/version", lambda r: web.json_response({"version": "test-1"}))
        app.router.add_post("/v1/completions", self.completions)
        app.router.add_post("/v1/embeddings", self.embeddings)
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.loop = asyncio.new_event_loop()
        self.runner = web.AppRunner(app)
        self.loop.run_until_complete(self.runner.setup())
        self.loop.run_until_complete(web.TCPSite(self.runner, "127.0.0.1", self.port).start())
        threading.Thread(target=self.loop.run_forever, daemon=True).start()
        self.url = f"http://127.0.0.1:{self.port}/v1"

    def stop(self) -> None:
        """Stop answering: the port is closed, as an engine that was shut down."""
        asyncio.run_coroutine_threadsafe(self.runner.cleanup(), self.loop).result(10)

    def _echo(self, prompt: str) -> dict:
        tok = self.lm.tokenizer(prompt, add_special_tokens=False, return_offsets_mapping=True)
        ids, offsets = tok["input_ids"], [start for start, _ in tok["offset_mapping"]]
        full = [*self.lm.bos_ids, *ids]
        with torch.inference_mode():
            logprobs = torch.log_softmax(self.lm.model(input_ids=torch.tensor([full])).logits[0].float(), -1)
        skip = len(self.lm.bos_ids)
        at = (lambda i: skip + i) if self.shifted else (lambda i: skip + i - 1)  # the logits that score token i
        token_lp = [None if at(i) < 0 else float(logprobs[at(i), t]) for i, t in enumerate(ids)]
        if self.no_echo:
            return {"text": prompt + " x", "finish_reason": "length", "logprobs": None}
        tokens = [prompt[a:b] for a, b in zip(offsets, offsets[1:] + [len(prompt)])]  # the echo spells the prompt
        return {"text": prompt + " x", "finish_reason": "length",
                "logprobs": {"tokens": tokens + [" x"], "token_logprobs": token_lp + [-1.0],
                             "text_offset": offsets + [len(prompt)]}}

    def _next(self, prompt: str) -> dict:
        ids = [*self.lm.bos_ids, *self.lm.tokenizer(prompt, add_special_tokens=False)["input_ids"]]
        with torch.inference_mode():
            logprobs = torch.log_softmax(self.lm.model(input_ids=torch.tensor([ids])).logits[0, -1].float(), -1)
        top = torch.topk(logprobs, 5)
        texts = [self.lm.tokenizer.decode([int(t)]) for t in top.indices]
        return {"text": texts[0], "finish_reason": "length",
                "logprobs": {"tokens": texts[:1], "token_logprobs": [float(top.values[0])], "text_offset": [len(prompt)],
                             "top_logprobs": [dict(zip(reversed(texts), reversed(top.values.tolist())))]}}

    async def completions(self, request):
        from aiohttp import web

        self.requests += 1
        if self.fail:
            self.fail -= 1
            if self.drop:  # the connection dropped mid-batch: no answer at all
                request.transport.close()
                raise ConnectionResetError("dropped by the test engine")
            return web.json_response({"error": "busy"}, status=self.status)
        body = await request.json()
        prompts = body["prompt"] if isinstance(body["prompt"], list) else [body["prompt"]]
        if self.single and isinstance(body["prompt"], list):
            return web.json_response({"error": "internal_server_error"}, status=500)
        if body.get("echo"):
            choices = [self._echo(p) for p in prompts]
        elif body.get("logprobs") and body["max_tokens"] == 1:  # one greedy token with its log-prob
            choices = [self._next(p) for p in prompts]
        else:
            gens = self.backend.generate(prompts, max_new_tokens=body["max_tokens"])
            choices = [{"text": g.text, "finish_reason": "stop" if g.finished else "length",
                        "logprobs": {"tokens": ["?"] * len(g.token_ids)}} for g in gens]
        answer = {"choices": [{**c, "index": i} for i, c in enumerate(choices)]}
        if self.mutate is not None and body.get("echo") and len(prompts) > 1:  # a ranking request: misbehave
            answer = self.mutate(answer)
            if isinstance(answer, web.StreamResponse):
                return answer
        return web.json_response(answer)

    async def embeddings(self, request):
        from aiohttp import web

        self.requests += 1
        body = await request.json()
        vectors = self.backend.embed(body["input"])
        answer = {"data": [{"index": i, "embedding": v.tolist()} for i, v in enumerate(vectors)]}
        if self.mutate_embeddings is not None:
            answer = self.mutate_embeddings(answer)
        return web.json_response(answer)


@pytest.fixture(scope="module")
def server(tiny_lm):
    return Server(tiny_lm)


def _records() -> list[StateRecord]:
    return [StateRecord(f"go to the {c} ball", (), f"You see a {c} ball {k} steps forward", ACTIONS)
            for c in ("red", "blue") for k in range(1, 4)]


def _rows(lm, tmp_path, name: str) -> dict:
    """The rows one annotation of `_records()` writes, by (task, prompt)."""
    import json

    from illm_tools.cache import layout

    cache = AnnotationCache(tmp_path / name)
    Annotator(lm, cache, model=lm.model, history_len=0).annotate_states(_records(), "BabyAI-GoToLocal-v0",
                                                                        "babyai-text@1")
    manifest = json.loads((tmp_path / name / "manifest.json").read_text())
    rows = [r for s in manifest["shards"] for r in layout.read_shard(tmp_path / name / s["name"]).to_pylist()]
    return {(r["task"], r["prompt"]): r for r in rows}


def test_annotation_through_the_endpoint_equals_the_transformers_backends(server, tiny_lm, tmp_path):
    spec = resolve_model("openai", "tiny", endpoint=server.url)
    remote = load_backend("openai", spec)
    assert isinstance(remote, OpenAIBackend) and remote.fingerprint["engine"] == "version test-1"
    assert remote.fingerprint["embedder"].startswith("endpoint /v1/embeddings")
    local = _rows(TransformersBackend(tiny_lm), tmp_path, "local")
    served = _rows(remote, tmp_path, "remote")
    assert set(local) == set(served) and len(local) == 2 * len(_records())
    for key, row in local.items():
        other = served[key]
        if row["task"] == "action":
            assert np.allclose(row["cand_logprob_sum"], other["cand_logprob_sum"], atol=1e-4), key
            assert row["cand_token_count"] == other["cand_token_count"]
        else:
            assert row["text"] == other["text"]  # greedy: the same summary
            assert len(other["embedding"]) == tiny_lm.hidden_size  # the endpoint's pooling (a documented deviation)


def test_failures_are_retried_then_refused_in_one_line_with_nothing_written(server, tmp_path):
    spec = resolve_model("openai", "tiny", endpoint=server.url)
    lm = OpenAIBackend(spec, retries=2)
    lm.client.backoff = 0.01
    server.fail = 2  # two 503s, then answers: retried
    assert len(lm.score(["Answer:"], [[" go", " stop"]])[0].sums) == 2
    server.fail = 10**6
    cache = AnnotationCache(tmp_path / "ann")
    with pytest.raises(EndpointError, match="failed 3 times .*503"):
        Annotator(lm, cache, model=spec, history_len=0).annotate_states(_records(), "BabyAI-GoToLocal-v0",
                                                                        "babyai-text@1")
    server.fail = 0
    assert len(AnnotationCache(tmp_path / "ann")) == 0  # nothing half-written


@pytest.mark.parametrize("how", ["500", "dropped"])
def test_an_engine_failing_mid_batch_is_one_line_and_nothing_half_written(server, tmp_path, how):
    """The first requests of a chunk are answered, the rest fail (a 500, or the connection cut):
    one line, and nothing of the chunk is in the cache."""
    spec = resolve_model("openai", "tiny", endpoint=server.url)
    lm = OpenAIBackend(spec, retries=1, concurrency=1)
    lm.client.backoff = 0.01
    answered = []
    real = lm._ranking

    def ranking_then_failing(item):
        if len(answered) == 2:
            server.fail, server.status, server.drop = 10**6, 500, how == "dropped"
        answered.append(item)
        return real(item)

    lm._ranking = ranking_then_failing
    cache = AnnotationCache(tmp_path / "ann")
    try:
        with pytest.raises(EndpointError, match="failed 2 times") as raised:
            Annotator(lm, cache, model=spec, history_len=0).annotate_states(_records(), "BabyAI-GoToLocal-v0",
                                                                            "babyai-text@1")
    finally:
        server.fail, server.status, server.drop = 0, 503, False
    assert len(answered) > 2 and "\n" not in str(raised.value)
    assert ("500" in str(raised.value)) == (how == "500")
    assert len(AnnotationCache(tmp_path / "ann")) == 0


def test_bad_endpoints_and_models_are_refused_in_one_line(server):
    with pytest.raises(UsageError, match="needs --endpoint"):
        resolve_model("openai", "tiny")
    with pytest.raises(UsageError, match="serves tiny, not 'llama'"):
        load_backend("openai", resolve_model("openai", "llama", endpoint=server.url))
    with pytest.raises(UsageError, match="no OpenAI-compatible server answers"):
        load_backend("openai", resolve_model("openai", "tiny", endpoint="http://127.0.0.1:9/v1"))
    with pytest.raises(UsageError, match="--embed-endpoint must be an http"):
        resolve_model("openai", "tiny", endpoint=server.url, embed_endpoint="localhost:8001")
    with pytest.raises(UsageError, match="^--endpoint is the openai backend.s: add --backend openai"):
        resolve_model("transformers", None, endpoint=server.url)
    with pytest.raises(UsageError, match="^--endpoint, --api-key-env are the openai backend.s"):
        resolve_model("oracle", None, endpoint=server.url, api_key_env="KEY")


@pytest.mark.parametrize("engine", [{"single": True}, {}])
def test_an_engine_taking_one_prompt_per_request_is_detected_and_answers_the_same(tiny_lm, tmp_path, engine, caplog):
    import logging

    server = Server(tiny_lm, name=f"tiny-{'single' if engine else 'list'}", **engine)
    spec = resolve_model("openai", server.name, endpoint=server.url)
    with caplog.at_level(logging.INFO, logger="illm_tools"):
        remote = load_backend("openai", spec)
    said = [r.getMessage() for r in caplog.records if "one prompt per request" in r.getMessage()]
    assert remote.engine.batches is not bool(engine) and remote.engine.aligned
    assert ("one prompt per request" in remote.fingerprint["engine"]) is bool(engine) and len(said) == int(bool(engine))
    local = _rows(TransformersBackend(tiny_lm), tmp_path, "local")
    served = _rows(remote, tmp_path, "remote")
    for key, row in local.items():
        if row["task"] == "action":
            assert np.allclose(row["cand_logprob_sum"], served[key]["cand_logprob_sum"], atol=1e-4), key
        else:
            assert row["text"] == served[key]["text"]


@pytest.mark.parametrize("engine", ["shifted", "no_echo"])
def test_ranking_through_an_engine_failing_the_alignment_check_is_refused_summaries_still_run(tiny_lm, tmp_path,
                                                                                              engine):
    server = Server(tiny_lm, name=f"tiny-{engine}", **{engine: True})
    spec = resolve_model("openai", server.name, endpoint=server.url)
    remote = load_backend("openai", spec)
    cache = AnnotationCache(tmp_path / "ann")
    with pytest.raises(EndpointError) as refused:
        Annotator(remote, cache, model=spec, history_len=0).annotate_states(_records(), "BabyAI-GoToLocal-v0",
                                                                            "babyai-text@1")
    line = str(refused.value)
    assert "\n" not in line and "cannot rank actions" in line and "--tasks summary" in line and "version test-1" in line
    assert ("shifted by one position" in line) is (engine == "shifted")
    assert len(AnnotationCache(tmp_path / "ann")) == 0  # nothing of a ranking it would get wrong
    Annotator(remote, cache, model=spec, history_len=0, tasks=["summary"]).annotate_states(
        _records(), "BabyAI-GoToLocal-v0", "babyai-text@1")
    assert len(AnnotationCache(tmp_path / "ann")) == len(_records())  # summaries through the same engine


def test_a_training_run_with_live_ranking_through_a_shifted_engine_is_refused_before_it_starts(tiny_lm, tmp_path):
    from typer.testing import CliRunner

    from cli.main import app

    server = Server(tiny_lm, name="tiny-shifted-train", shifted=True)
    out = CliRunner().invoke(app, ["train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--backend", "openai",
                                   "--model", server.name, "--endpoint", server.url, "--history", "0", "--new-setup",
                                   "--cache", str(tmp_path / "ann"), "--frames", "64", "--num-envs", "2",
                                   "--num-steps", "32", "--out", str(tmp_path / "run")])
    assert out.exit_code == 1 and "cannot rank actions" in out.output and "Traceback" not in out.output
    assert not (tmp_path / "run").exists() and not list((tmp_path / "ann").glob("shard-*"))


def test_a_pooling_endpoint_of_the_same_weights_embeds_the_summaries(tiny_lm, tmp_path):
    """--embed-endpoint: the texts' embeddings come from a second server of the same weights (vLLM's
    pooling runner); one serving other weights, or none, is refused in one line before anything runs."""
    completions = Server(tiny_lm, root="/models/tiny")
    pooling, other = Server(tiny_lm, root="/models/tiny"), Server(tiny_lm, root="/models/another")
    remote = load_backend("openai", resolve_model("openai", "tiny", endpoint=completions.url,
                                                  embed_endpoint=pooling.url))
    assert remote.fingerprint["embedder"].startswith("pooling endpoint, /models/tiny")
    before = pooling.requests
    vectors = remote.embed(["You see a red ball", "go forward"])
    assert pooling.requests > before and vectors.shape == (2, tiny_lm.hidden_size)
    with pytest.raises(UsageError, match="serves /models/another as 'tiny'.*same weights"):
        load_backend("openai", resolve_model("openai", "tiny", endpoint=completions.url, embed_endpoint=other.url))
    with pytest.raises(UsageError, match="pooling endpoint http://127.0.0.1:9/v1 gives no embeddings"):
        load_backend("openai", resolve_model("openai", "tiny", endpoint=completions.url,
                                             embed_endpoint="http://127.0.0.1:9/v1"))


def test_a_cache_annotated_through_an_engine_trains_with_the_engine_stopped_under_any_address(tiny_lm, tmp_path,
                                                                                             caplog):
    """Issue 54: annotated at 127.0.0.1, more states through `localhost`: one setup (the weights'
    fingerprint, not the address); with the engine stopped, `illm cache info` lists it without
    asking anything and `illm train --live-budget 0` adopts it and trains on its targets."""
    import json

    from typer.testing import CliRunner

    from cli.main import app
    from illm_tools.collect import CollectConfig, collect

    runner = CliRunner()
    engine = Server(tiny_lm)
    traj, ann = tmp_path / "traj", tmp_path / "ann"
    collect(CollectConfig(env_id="BabyAI-GoToRedBallNoDists-v0", out=traj, steps=256, num_envs=4, seed=0))
    for url, limit in ((engine.url, 8), (engine.url.replace("127.0.0.1", "localhost"), 12)):
        done = runner.invoke(app, ["annotate", str(traj), "--cache", str(ann), "--backend", "openai", "--model", "tiny",
                                   "--endpoint", url, "--history", "0", "--limit", str(limit)])
        assert done.exit_code == 0, done.output
    engine.stop()
    said = trains_with_the_engine_stopped(ann, tmp_path / "run", 12, reach=("--endpoint", engine.url))
    assert "adopting the cache's setup: --backend openai --model tiny" in said
    with caplog.at_level(logging.WARNING, logger="illm_tools.rl.run"):
        live = runner.invoke(app, ["train", "--env", "BabyAI-GoToRedBallNoDists-v0", "--method", "illm", "--cache",
                                   str(ann), "--live-budget", "4", "--num-envs", "4", "--num-steps", "32", "--frames",
                                   "128", "--seed", "1", "--out", str(tmp_path / "run-live"), "--endpoint", engine.url])
    assert live.exit_code == 0, live.output  # the cache's targets alone, said in one line
    said = [r.getMessage() for r in caplog.records if "trains from the cache's targets alone" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("no OpenAI-compatible server answers at http://"), said


def _nan(answer):
    answer["choices"][0]["logprobs"]["token_logprobs"][-2] = float("nan")  # sent as NaN, which JSON lacks
    return answer


def _unscored(answer):
    answer["choices"][1]["logprobs"]["token_logprobs"][-2] = None
    return answer


def _misaligned(answer):
    offsets = answer["choices"][0]["logprobs"]["text_offset"]
    offsets[-2] = offsets[-3]  # two tokens at one offset: the log-probs no longer say which text they score
    return answer


def _inf(answer):
    from aiohttp import web

    answer["choices"][0]["logprobs"]["token_logprobs"][-2] = -123.25
    text = json.dumps(answer).replace("-123.25", "1e400")  # valid JSON, read as infinity
    return web.Response(text=text, content_type="application/json")


def _duplicate(answer):
    answer["choices"][1]["index"] = 0
    return answer


def _missing(answer):
    answer["choices"].pop()
    return answer


def _redirect(answer):
    from aiohttp import web

    return web.Response(status=302, headers={"Location": "http://127.0.0.1:9/v1/completions"})


def _short_embeddings(answer):
    for d in answer["data"]:
        d["embedding"] = d["embedding"][:-1]
    return answer


@pytest.mark.parametrize("mutate,said", [
    (_nan, "answered what is not JSON (NaN is not a finite number)"), (_inf, "not all finite numbers at most 0"),
    (_unscored, "not all finite numbers at most 0"), (_misaligned, "token offsets that are not increasing"),
    (_duplicate, "each index once is expected"), (_missing, "each index once is expected"),
    (_redirect, "answered a redirect (302), which illm does not follow")])
def test_an_engines_malformed_ranking_is_refused_in_one_line_naming_it(tiny_lm, tmp_path, mutate, said):
    engine = Server(tiny_lm)
    spec = resolve_model("openai", "tiny", endpoint=engine.url)
    remote = load_backend("openai", spec)
    engine.mutate = mutate
    with pytest.raises(EndpointError, match=re.escape(said)) as e:
        remote.score(["Valid actions: turn left, go forward. Action:"], [[" turn left", " go forward"]])
    assert engine.url in str(e.value) and len(str(e.value).splitlines()) == 1
    engine.stop()


def test_an_engines_embeddings_of_another_width_or_an_answer_too_large_are_refused(tiny_lm, monkeypatch):
    from illm_tools.llm import openai_wire

    engine = Server(tiny_lm)
    remote = load_backend("openai", resolve_model("openai", "tiny", endpoint=engine.url))
    engine.mutate_embeddings = _short_embeddings
    with pytest.raises(EndpointError, match="not finite vectors of 64 dimensions"):
        remote.embed(["go to the red ball"])
    engine.mutate_embeddings = None
    monkeypatch.setattr(openai_wire, "MAX_ANSWER_BYTES", 200)  # a cap this answer passes
    with pytest.raises(EndpointError, match="answered more than 0 MiB: refused"):
        remote.embed(["go to the red ball"])
    engine.stop()
