"""The openai backend: annotation through an OpenAI-compatible completions endpoint, so the LLM can
run on a serving engine built for it (vLLM, SGLang, TGI, llama.cpp's server: continuous batching,
prefix caching, a model sharded over GPUs) instead of in illm's own process.

`--backend openai --model NAME --endpoint URL [--api-key-env VAR]`: NAME is the model as the server
serves it (`GET /v1/models`), URL the server's OpenAI base (`http://host:8000/v1`), VAR the
environment variable holding its API key (default OPENAI_API_KEY; none needed for a local
server). The model spec is "NAME@URL" (and "#VAR"), so every place that names a model names it; a
spec read from a cache's rows is an identity only, never reached (`illm_tools.tasks.served.reached_model`).

- Ranking (`score`): one `POST /v1/completions` per state with its candidates as a list of
  prompts, context + candidate each, `echo: true, logprobs: 1, max_tokens: 1, temperature: 0`:
  the engine returns every prompt token's log-probability with its character offset, and a
  candidate's score is the sum over the tokens that end after the context (context and candidate
  tokenised together, as `illm_tools.llm.scoring` does). The candidates of a state share their
  context, so an engine's prefix cache computes it once. Which engines give prompt log-probs this
  way, as their documentation reads: vLLM (`echo` with `logprobs` on /v1/completions; also its
  `prompt_logprobs` extension); TGI only in its native API (`decoder_input_details`), not its OpenAI
  one; llama.cpp's server and SGLang: check the version in use (illm refuses an answer without
  prompt log-probs in one line).
- Text tasks (`generate`): greedy completions (`temperature: 0`) of at most the task's tokens, a
  batch of prompts per request; `finish_reason` "length" marks a cut text.
- Embeddings of the texts: from the same model's pooling endpoint (`POST /v1/embeddings`): the
  completions endpoint's own where the engine offers one, or `--embed-endpoint URL`, a second server
  of the same weights with a pooling runner (vLLM: `--runner pooling --convert embed` with mean
  pooling, unnormalised: the mean last hidden state over the text's tokens, as
  `illm_tools.llm.generation.embed_texts` computes it in-process; a pooling endpoint serving other
  weights is refused in one line); else from the local sentence model (all-MiniLM-L6-v2). Each
  deviates from the paper's mean-pooled hidden state over the generated tokens read with their
  prompt (the transformers backend's), which a completions endpoint does not return: the pooled
  text is read without its prompt. The fingerprint says which embedder was used.
- Requests go `concurrency` at a time (threads: the waiting is on the network). Annotation writes
  a chunk only when all of its answers are in, so a failure leaves nothing half-written in the cache.

What is asked of the engine on connecting (its fingerprint, whether it takes a list of prompts,
whether its echoed log-probs are aligned), how requests are retried and how every answer is checked
before it is stored is the wire protocol's, `illm_tools.llm.openai_wire`.

Hop mode is refused: an endpoint takes text, not input embeddings.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.llm.openai_answers import candidate_logprobs, embedding_vectors, generated_text, ordered_choices
from illm_tools.llm.openai_wire import (Client, address_of, check_ranking, describe_offline, embed_url, engine_probe,
                                        identity, openai_spec, parse_spec, served_as, served_fingerprint)

NAME = "openai"


class OpenAIBackend:
    """The backend protocol over an OpenAI-compatible endpoint (see the module docstring)."""

    name = NAME
    device = "remote"
    shares_prefix = False
    computes = False
    """The dtype and quantisation are the server's: `--dtype`/`--quant` are ignored."""
    chunk_states = 256
    """States per written shard in bulk annotation (an engine answers hundreds a second on a GPU)."""

    model_options = ("endpoint", "api_key_env", "embed_endpoint")
    """Where the engine is and which variable holds its key go into the model spec (`model_spec`)."""

    @staticmethod
    def model_spec(model: str | None, *, endpoint: str | None = None, api_key_env: str | None = None,
                   embed_endpoint: str | None = None) -> str:
        """The spec "NAME@URL[#VAR][;embed=URL]" of `--model` and the options."""
        if model is None:
            raise UsageError("--backend openai needs --model, the model's name as the server serves it")
        if "@" in model and endpoint is None:
            parse_spec(model)
            return model
        return openai_spec(model, endpoint, api_key_env, embed_endpoint)

    @staticmethod
    def selecting_options(model: str) -> str:
        url = address_of(model)  # None: a shared file's identity, which names no address
        name, pooled = served_as(model)
        embed = (embed_url(model) if url else "URL") if pooled else None
        return f"--backend openai --model {name} --endpoint {url or 'URL'}" + (f" --embed-endpoint {embed}" if embed else "")

    # --- a served model in a shared cache: an identity, never an address (`illm_tools.tasks.served`) ---------
    identity = staticmethod(identity)
    served_as = staticmethod(served_as)

    @staticmethod
    def address_of(spec: str) -> str | None:
        """The engine URL a spec of this machine's annotator names; None for an identity or another
        backend's model."""
        return address_of(spec) if describe_offline(spec) is not None else None

    @staticmethod
    def reached_model(model: str, given: dict, where) -> dict:
        """An adopted served model: its served name alone, reached where the user's own options
        (`given`) say: the address and key variable of the spec its rows were written under are never
        read, and without --endpoint it is refused in one line naming the options to give."""
        name, pooled = served_as(model)
        missing = [option for option, needed in (("--endpoint URL (your engine's OpenAI base)", "endpoint"),
                                                 ("--embed-endpoint URL (its summaries were embedded by a pooling "
                                                  "endpoint)", "embed_endpoint" if pooled else None))
                   if needed and not given.get(needed)]
        if missing:
            raise UsageError(f"the cache {where} holds annotations of {name!r} served by an OpenAI-compatible engine, "
                             f"and a cache never says where a request goes: give {' and '.join(missing)}, with "
                             "--api-key-env VAR if it needs a key, or choose the model with --backend and --model")
        return {"model": name}

    def __init__(self, spec: str, *, concurrency: int = 16, timeout: float = 120.0, retries: int = 4):
        self.model = spec
        self.served, url, key = parse_spec(spec)
        self.fingerprint = {k: v for k, v in served_fingerprint(spec).items() if k != "embedding_dim"}
        dim = served_fingerprint(spec)["embedding_dim"]
        self.client = Client(url, key, timeout=timeout, retries=retries)
        pooled = embed_url(spec)
        self.embed_client = Client(pooled, key, timeout=timeout, retries=retries) if pooled else self.client
        self.concurrency = concurrency
        self.engine = engine_probe(spec)
        self.remote_embeddings = dim is not None
        self.hidden_size = int(dim) if dim else self._local_dim()

    @staticmethod
    def _local_dim() -> int:
        from illm_tools.llm.oracle import _embedding_dim

        return _embedding_dim()

    @classmethod
    def load(cls, model: str, *, dtype: str = "float32", quant: str = "none", device: str = "cpu", cache_dir=None,
             batch_tokens=None):
        return cls(model)

    @staticmethod
    def model_fingerprint(model: str, *, dtype: str = "float32", quant: str = "none") -> dict:
        return {k: v for k, v in served_fingerprint(model).items() if k != "embedding_dim"}

    @staticmethod
    def model_hidden_size(model: str) -> int:
        dim = served_fingerprint(model)["embedding_dim"]
        return int(dim) if dim else OpenAIBackend._local_dim()

    @staticmethod
    def check_use(env_id: str, renderer: str) -> None:
        if renderer.startswith("hop@"):
            raise UsageError("--backend openai sends text; --mode hop splices input embeddings into the model, which an "
                             "endpoint does not take: use --backend transformers for hop")

    # --- requests ----------------------------------------------------------------------------------
    def _map(self, fn, items: Sequence) -> list:
        if len(items) <= 1 or self.concurrency <= 1:
            return [fn(x) for x in items]
        with ThreadPoolExecutor(max_workers=min(self.concurrency, len(items))) as pool:
            return list(pool.map(fn, items))

    def _choices(self, prompts: list[str], body: dict) -> list[dict]:
        """The engine's choices for `prompts` (one request, or one per prompt where the engine takes a
        single prompt), in prompt order."""
        if not self.engine.batches and len(prompts) > 1:
            return [c for p in prompts for c in self._choices([p], body)]
        answer, _ = self.client.call("/completions", {"model": self.served, **body,
                                                      "prompt": prompts if self.engine.batches else prompts[0]})
        return ordered_choices(answer, len(prompts), f"{self.client.url}/completions")

    @staticmethod
    def describe_offline(model: str) -> dict | None:
        """A cache row's model as its options without asking the engine (`openai_wire.describe_offline`)."""
        return describe_offline(model)

    @staticmethod
    def check_ranking(model: str) -> None:
        """Refuse, in one line, ranking through an engine whose echoed log-probs failed the
        connection's probe (`openai_wire`); text tasks need no check."""
        check_ranking(model)

    def _ranking(self, item):
        from illm_tools.llm.scoring import CandidateScores

        context, candidates = item
        prompts = [context + c for c in candidates]
        choices = self._choices(prompts, {"max_tokens": 1, "temperature": 0, "echo": True, "logprobs": 1})
        where = f"{self.client.url}/completions"
        return CandidateScores.from_logprobs([candidate_logprobs(choice, prompt, len(context), where)
                                              for prompt, choice in zip(prompts, choices)])

    def score(self, contexts, candidates, *, batch_size: int = 8):
        check_ranking(self.model)
        return self._map(self._ranking, list(zip(contexts, [list(c) for c in candidates])))

    def _completion(self, item):
        prompts, max_new_tokens = item
        choices = self._choices(prompts, {"temperature": 0, "max_tokens": max_new_tokens, "logprobs": 0})
        return [generated_text(c, f"{self.client.url}/completions") for c in choices]

    def generate(self, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        from illm_tools.llm.generation import Generation

        size = batch_size if self.engine.batches else 1  # one prompt per request: `concurrency` requests at a time
        batches = [(list(prompts[i:i + size]), max_new_tokens) for i in range(0, len(prompts), size)]
        texts = [t for batch in self._map(self._completion, batches) for t in batch]
        embeddings = self.embed([t for t, _, _ in texts])
        return [Generation(text, list(range(n)), finished, emb) for (text, n, finished), emb in zip(texts, embeddings)]

    def score_and_generate(self, contexts, candidates, prompts, *, max_new_tokens: int = 64, batch_size: int = 8):
        return (self.score(contexts, candidates, batch_size=batch_size),
                self.generate(prompts, max_new_tokens=max_new_tokens, batch_size=batch_size))

    def embed(self, texts, *, batch_size: int = 32):
        texts = list(texts)
        if not texts:
            return np.zeros((0, self.hidden_size), np.float32)
        if not self.remote_embeddings:
            from illm_tools.llm.sentence import shared_embedder

            return shared_embedder().encode(texts)

        def call(chunk):
            answer, _ = self.embed_client.call("/embeddings", {"model": self.served, "input": chunk})
            return embedding_vectors(answer, len(chunk), self.hidden_size, f"{self.embed_client.url}/embeddings")

        chunks = [texts[i:i + batch_size] for i in range(0, len(texts), batch_size)]
        return np.asarray([e for part in self._map(call, chunks) for e in part], dtype=np.float32)

    def _no_hop(self, *_args, **_kwargs):
        self.check_use("", "hop@")

    input_embeddings = last_hidden = spliced = _no_hop
