"""The openai backend: annotation through an OpenAI-compatible completions endpoint, so the LLM can
run on a serving engine built for it (vLLM, SGLang, TGI, llama.cpp's server: continuous batching,
prefix caching, a model sharded over GPUs) instead of in illm's own process.

`--backend openai --model NAME --endpoint URL [--api-key-env VAR]`: NAME is the model as the server
serves it (`GET /v1/models`), URL the server's OpenAI base (`http://host:8000/v1`), VAR the
environment variable holding its API key (default OPENAI_API_KEY; none needed for a local
server). The model spec is "NAME@URL" (and "#VAR"), so every place that names a model names it.

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
- The fingerprint carries the served model's name, the engine and its version (`GET /version`,
  vLLM's; else the `Server` header), the embedder, and never the URL (the same engine and model on
  another host answer the same) nor the key.
- On connecting (once per process and endpoint), two probes (`openai_engine._probe_engine`):
  * whether the engine takes a list of prompts per request (vLLM, SGLang do; llama-cpp-python's
    server answers 500): where it does not, every prompt goes alone, still `concurrency` at a time.
    Said in one line and written into the fingerprint's engine description.
  * whether its echoed prompt log-probs are aligned: generate one token after a fixed context
    with the log-probs of the likely next tokens, then score context + one of them with echo; the
    two log-probs of that token must agree within `ALIGNMENT_TOLERANCE`. An engine that scores token i with the logits at position i
    instead of i-1 (llama-cpp-python 0.3.x) fails, and ranking through it is refused in one line
    before anything is annotated (its rankings would be noise); summaries still run through it.
- An engine's answers are checked before anything is stored, each failure one line naming the
  engine's URL: JSON without NaN or Infinity and at most `MAX_ANSWER_BYTES`; one choice per prompt,
  each index once; a candidate's echoed tokens one run in increasing offsets, each with a finite
  log-prob at most 0 (a candidate with no scored token would otherwise sum to 0 and win); an
  embedding finite and of the width the engine gave at connection. A redirect is never followed,
  so the API key goes to the configured endpoint only.
- Requests go `concurrency` at a time (threads: the waiting is on the network), each with a
  timeout; 429 and 5xx answers and lost connections are retried with exponential backoff
  (`retries` times), then refused in one line. Annotation writes a chunk only when all of its
  answers are in, so a failure leaves nothing half-written in the cache.

Hop mode is refused: an endpoint takes text, not input embeddings.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from illm_tools.errors import UsageError
from illm_tools.llm.openai_engine import (_ENGINES, Client, EndpointError, _check_ranking,  # noqa: F401 (re-exported)
                                          _fingerprint, describe_offline, embed_url, openai_spec, parse_spec)

NAME = "openai"
log = logging.getLogger(__name__)


class OpenAIBackend:
    """The backend protocol over an OpenAI-compatible endpoint (see the module docstring)."""

    name = NAME
    device = "remote"
    shares_prefix = False
    computes = False
    """The dtype and quantisation are the server's: `--dtype`/`--quant` are ignored."""
    chunk_states = 256
    """States per written shard in bulk annotation (an engine answers hundreds a second on a GPU)."""

    def __init__(self, spec: str, *, concurrency: int = 16, timeout: float = 120.0, retries: int = 4):
        self.model = spec
        self.served, url, key = parse_spec(spec)
        self.fingerprint = {k: v for k, v in _fingerprint(spec).items() if k != "embedding_dim"}
        dim = _fingerprint(spec)["embedding_dim"]
        self.client = Client(url, key, timeout=timeout, retries=retries)
        pooled = embed_url(spec)
        self.embed_client = Client(pooled, key, timeout=timeout, retries=retries) if pooled else self.client
        self.concurrency = concurrency
        self.engine = _ENGINES[spec]
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
        return {k: v for k, v in _fingerprint(model).items() if k != "embedding_dim"}

    @staticmethod
    def model_hidden_size(model: str) -> int:
        dim = _fingerprint(model)["embedding_dim"]
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
        choices = answer.get("choices")
        indices = [c.get("index") if isinstance(c, dict) else None for c in choices or []]
        if not isinstance(choices, list) or sorted(i for i in indices if type(i) is int) != list(range(len(prompts))) \
                or len(indices) != len(prompts):
            raise EndpointError(f"{self.client.url}/completions answered choices {indices[:8]} for {len(prompts)} prompts "
                                "(each index once is expected): not used")
        return sorted(choices, key=lambda c: c["index"])

    @staticmethod
    def describe_offline(model: str) -> dict | None:
        """A cache row's model as its options without asking the engine (`openai_engine.describe_offline`)."""
        return describe_offline(model)

    @staticmethod
    def check_ranking(model: str) -> None:
        """Refuse, in one line, ranking through an engine whose echoed log-probs failed the
        connection's probe (see the module docstring); text tasks need no check."""
        _check_ranking(model)

    def _ranking(self, item):
        from illm_tools.llm.scoring import CandidateScores

        context, candidates = item
        prompts = [context + c for c in candidates]
        choices = self._choices(prompts, {"max_tokens": 1, "temperature": 0, "echo": True, "logprobs": 1})
        out = []
        for prompt, choice in zip(prompts, choices):
            lp = choice.get("logprobs") or {}
            offsets, logprobs = lp.get("text_offset"), lp.get("token_logprobs")
            if not offsets or logprobs is None:
                raise EndpointError(f"{self.client.url}/completions gave no prompt log-probabilities (echo with logprobs): "
                                    "this engine cannot rank candidates; vLLM can (docs/scale.md)")
            out.append(self._candidate_logprobs(prompt, len(context), offsets, logprobs))
        return CandidateScores.from_logprobs(out)

    def _candidate_logprobs(self, prompt: str, start: int, offsets, logprobs) -> list[float]:
        """The log-probs of the echoed tokens that end after the context (`start` characters): one
        run of consecutive tokens, each scored with a finite log-prob, in increasing offsets; else
        refused in one line naming the engine (a candidate with no scored token would sum to 0)."""
        import math

        where = f"{self.client.url}/completions"
        if len(offsets) != len(logprobs) or any(type(o) is not int for o in offsets) or \
                any(b <= a for a, b in zip(offsets, offsets[1:])):
            raise EndpointError(f"{where} answered token offsets that are not increasing, one per log-prob: not used")
        ends = list(offsets[1:]) + [len(prompt) + 10**9]
        inside = [i for i in range(len(offsets)) if offsets[i] < len(prompt)]  # the echo, without a generated token
        mine = [i for i in inside if ends[i] > start]
        if not mine or mine != list(range(mine[0], inside[-1] + 1)):
            raise EndpointError(f"{where} answered no contiguous tokens for a candidate ({prompt[start:][:40]!r}): not used")
        values = [logprobs[i] for i in mine]
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v > 0 for v in values):
            raise EndpointError(f"{where} answered a candidate's token log-probs {values[:6]}, not all finite numbers "
                                "at most 0: not used")
        return [float(v) for v in values]

    def score(self, contexts, candidates, *, batch_size: int = 8):
        _check_ranking(self.model)
        return self._map(self._ranking, list(zip(contexts, [list(c) for c in candidates])))

    def _completion(self, item):
        prompts, max_new_tokens = item
        choices = self._choices(prompts, {"temperature": 0, "max_tokens": max_new_tokens, "logprobs": 0})
        return [(c.get("text", ""), len((c.get("logprobs") or {}).get("tokens") or []),
                 c.get("finish_reason") != "length") for c in choices]

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
            data = answer.get("data")
            where = f"{self.embed_client.url}/embeddings"
            if not isinstance(data, list) or sorted(d.get("index", -1) for d in data if isinstance(d, dict)) != \
                    list(range(len(chunk))):
                raise EndpointError(f"{where} answered {len(data) if isinstance(data, list) else 'no'} embeddings for "
                                    f"{len(chunk)} texts (each index once is expected): not used")
            vectors = [d["embedding"] for d in sorted(data, key=lambda d: d["index"])]
            array = np.asarray(vectors, dtype=np.float64) if all(isinstance(v, list) for v in vectors) else None
            if array is None or array.ndim != 2 or array.shape[1] != self.hidden_size or not np.isfinite(array).all():
                raise EndpointError(f"{where} answered embeddings that are not finite vectors of {self.hidden_size} "
                                    "dimensions (the width it gave when illm connected): not used")
            return list(array.astype(np.float32))

        chunks = [texts[i:i + batch_size] for i in range(0, len(texts), batch_size)]
        return np.asarray([e for part in self._map(call, chunks) for e in part], dtype=np.float32)

    def _no_hop(self, *_args, **_kwargs):
        self.check_use("", "hop@")

    input_embeddings = last_hidden = spliced = _no_hop
