"""The wire protocol with an OpenAI-compatible engine: the model spec "NAME@URL[#VAR][;embed=URL]",
the HTTP client (through `illm_tools.web`, with its timeout and retries), the served model's
identity, the connection probes, and the checks of what the engine answers. The backend that ranks
and generates over it is `illm_tools.llm.openai`; kept apart so that what is asked of an engine,
and what its answers must be, read in one place whichever backend asks.

- The fingerprint (`served_fingerprint`) carries the served model's name, the engine and its
  version (`GET /version`, vLLM's; else the `Server` header), the embedder, and never the URL (the
  same engine and model on another host answer the same) nor the key.
- On connecting (once per process and endpoint), two probes (`_probe_engine`):
  * whether the engine takes a list of prompts per request (vLLM, SGLang do; llama-cpp-python's
    server answers 500): where it does not, every prompt goes alone, still `concurrency` at a time.
    Said in one line and written into the fingerprint's engine description.
  * whether its echoed prompt log-probs are aligned: generate one token after a fixed context
    with the log-probs of the likely next tokens, then score context + one of them with echo; the
    two log-probs of that token must agree within `ALIGNMENT_TOLERANCE`. An engine that scores
    token i with the logits at position i instead of i-1 (llama-cpp-python 0.3.x) fails, and
    ranking through it is refused in one line before anything is annotated (`check_ranking`: its
    rankings would be noise); summaries still run through it.
- An engine's answers are checked before anything is stored (`illm_tools.llm.openai_answers`, each
  failure one line naming the engine's URL); here, what every answer gets: JSON without NaN or
  Infinity, at most `MAX_ANSWER_BYTES` and not nested too deep to read. A redirect is never followed,
  so the API key goes to the configured endpoint only. The engine's URL and key variable come from
  the user's own options (a cache row's model spec is an identity, never adopted with its address:
  `illm_tools.tasks.served`).
- Each request has a timeout; 429 and 5xx answers and lost connections are retried with
  exponential backoff (`retries` times), then refused in one line.
"""

from __future__ import annotations

import http.client
import json
import logging
import os
import re
import time
import urllib.error
import urllib.request
from dataclasses import dataclass

from illm_tools.errors import EngineUnreachableError, IllmError, UsageError
from illm_tools.web import NO_REDIRECTS

DEFAULT_KEY_ENV = "OPENAI_API_KEY"
_SPEC = re.compile(r"^(?P<model>[^@#\s]+)@(?P<url>https?://[^#;\s]+?)/?(?:#(?P<key>[A-Za-z_][A-Za-z0-9_]*))?"
                   r"(?:;embed=(?P<embed>https?://[^#;\s]+?)/?)?$")
IDENTITY_PREFIX = "openai:"
_IDENTITY = re.compile(r"^openai:(?P<model>[^@#\s;]+)(?P<embed>;embed)?$")
_FINGERPRINTS: dict[str, dict] = {}
_ENGINES: dict[str, "EngineProbe"] = {}
log = logging.getLogger(__name__)

ALIGNMENT_CONTEXTS = ("One, two, three, four, five,", "The capital of France is")
"""The alignment probe's contexts, tried in turn until one of its likely next tokens stays one token
when scored with it; whatever the token, the check compares the engine with itself."""
ALIGNMENT_TOP = 5
"""Likely next tokens asked for (`logprobs` of the generation): the probe scores the most likely one
that is whole text and stays one token after the context (a byte-level token is not)."""
ALIGNMENT_TOLERANCE = 0.1
"""Nats by which the generated token's log-prob and the echoed one may differ. The two come from
the same weights through two paths (a decode step; a prefill), which differ by rounding: under
0.01 nats in float32, a few hundredths in bfloat16 on a GPU. A shifted echo is off by nats (8.3 for
SmolLM2-135M's " six" under llama-cpp-python 0.3.x)."""
MAX_ANSWER_BYTES = 256 * 2**20
"""The largest answer read from an engine (a batch of echoed prompts with their log-probs is a few MiB)."""


class EndpointError(IllmError):
    """The endpoint failed a request after its retries, or answered something illm cannot use."""


def _one_line(text: str, limit: int = 200) -> str:
    """What an engine said, for a one-line error: its whitespace (line breaks included) one space, cut."""
    return " ".join(text.split())[:limit]


def _no_constant(name: str):
    raise ValueError(f"{name} is not a finite number")



# --- the model spec ------------------------------------------------------------------------------
def describe_offline(spec: str) -> dict | None:
    """A cache row's served model as its options, from the spec alone ({"backend", "model", "dtype",
    "quant"}; None when `spec` is no openai spec): the engine is never asked, so a cache annotated
    through an engine is read, listed and adopted with the engine stopped. The row's fingerprint
    hash, not its URL, is the model's identity. A spec is the annotator's "NAME@URL[#VAR][;embed=URL]"
    or, in a shared file, its address-free `identity` "openai:NAME[;embed]"."""
    if _SPEC.match(spec or "") is None and _IDENTITY.match(spec or "") is None:
        return None
    return {"backend": "openai", "model": spec, "dtype": "float32", "quant": "none"}


def served_as(spec: str) -> tuple[str, bool]:
    """What a spec serves whatever its address: the model's served name, and whether a pooling
    endpoint embeds (another embedder, another fingerprint); an `identity` says both."""
    shared = _IDENTITY.match(spec or "")
    if shared is not None:
        return shared.group("model"), shared.group("embed") is not None
    return parse_spec(spec)[0], embed_url(spec) is not None


def identity(spec: str) -> str:
    """A served model's spec as a shared cache names it: "openai:NAME", with ";embed" where a pooling
    endpoint embedded its summaries: what it serves (`served_as`), never where or with which key
    (`illm cache export` writes it; an import refuses the address form)."""
    name, pooled = served_as(spec)
    return f"{IDENTITY_PREFIX}{name}" + (";embed" if pooled else "")


def address_of(spec: str) -> str | None:
    """The engine URL a spec written by this machine's annotator names; None for an `identity`."""
    return None if _IDENTITY.match(spec or "") else parse_spec(spec)[1]


def openai_spec(model: str, endpoint: str | None, api_key_env: str | None = None,
                embed_endpoint: str | None = None) -> str:
    """The model spec "NAME@URL[#VAR][;embed=URL]" of a served model."""
    if not endpoint:
        raise UsageError("--backend openai needs --endpoint URL (the server's OpenAI base, e.g. http://127.0.0.1:8000/v1)")
    if not endpoint.startswith(("http://", "https://")):
        raise UsageError(f"--endpoint must be an http(s) URL, got {endpoint!r}")
    if embed_endpoint and not embed_endpoint.startswith(("http://", "https://")):
        raise UsageError(f"--embed-endpoint must be an http(s) URL, got {embed_endpoint!r}")
    spec = (f"{model}@{endpoint.rstrip('/')}" + (f"#{api_key_env}" if api_key_env else "")
            + (f";embed={embed_endpoint.rstrip('/')}" if embed_endpoint else ""))
    parse_spec(spec)
    return spec


def embed_url(spec: str) -> str | None:
    """The pooling endpoint's base URL of a spec (`--embed-endpoint`), or None."""
    parse_spec(spec)
    return _SPEC.match(spec).group("embed")


def parse_spec(spec: str) -> tuple[str, str, str]:
    """(served model name, base URL, key variable) of a spec; anything else refused in one line."""
    if _IDENTITY.match(spec or ""):
        raise UsageError(f"{spec!r} names a served model as a shared cache does, without its address: give "
                         "--endpoint URL (your engine serving it), with --api-key-env VAR if it needs a key")
    m = _SPEC.match(spec or "")
    if m is None:
        raise UsageError(f"--backend openai names its model as the server serves it, with --endpoint URL (model spec "
                         f"NAME@URL), not {spec!r}")
    return m.group("model"), m.group("url"), m.group("key") or DEFAULT_KEY_ENV


# --- requests ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EngineProbe:
    """What the connection probes found (`_probe_engine`)."""

    batches: bool
    """The engine takes a list of prompts in one request."""
    aligned: bool | None
    """Its echoed prompt log-probs agree with its generation's (None: it gives no prompt log-probs)."""
    detail: str
    """The probe's figures, for the refusal's line."""


class Client:
    """JSON over HTTP to one endpoint, with a timeout and retries (urllib: a few short calls per
    batch need no more)."""

    def __init__(self, url: str, key_env: str = DEFAULT_KEY_ENV, *, timeout: float = 120.0, retries: int = 4,
                 backoff: float = 0.5):
        self.url, self.key, self.timeout, self.retries, self.backoff = url, os.environ.get(key_env), timeout, retries, backoff

    def call(self, path: str, body: dict | None = None, *, root: bool = False) -> tuple[dict, dict]:
        """(JSON answer, headers named in lower case) of GET (body None) or POST `path` under the base URL (or
        its root)."""
        base = re.sub(r"/v1$", "", self.url) if root else self.url
        headers = {"Content-Type": "application/json", **({"Authorization": f"Bearer {self.key}"} if self.key else {})}
        data = None if body is None else json.dumps(body).encode()
        last = ""
        for attempt in range(self.retries + 1):
            request = urllib.request.Request(base + path, data=data, headers=headers,
                                             method="GET" if body is None else "POST")
            try:
                with NO_REDIRECTS.open(request, timeout=self.timeout) as response:
                    raw = response.read(MAX_ANSWER_BYTES + 1)
                    if len(raw) > MAX_ANSWER_BYTES:
                        raise EndpointError(f"{base + path} answered more than {MAX_ANSWER_BYTES // 2**20} MiB: refused")
                    try:
                        answer = json.loads(raw or b"{}", parse_constant=_no_constant)
                    except RecursionError:  # the decoder's own limit (about 1,000 levels; an answer nests 5)
                        raise EndpointError(f"{base + path} answered JSON nested too deep to read: refused") from None
                    if not isinstance(answer, dict):
                        raise EndpointError(f"{base + path} answered what is not a JSON object")
                    return answer, {k.lower(): v for k, v in response.headers.items()}
            except urllib.error.HTTPError as e:
                detail = _one_line(e.read(2000).decode(errors="replace"))
                if 300 <= e.code < 400:
                    raise EndpointError(f"{base + path} answered a redirect ({e.code}), which illm does not follow (the "
                                        "key goes to --endpoint only): give the engine's own URL") from None
                if e.code != 429 and e.code < 500:
                    raise EndpointError(f"{base + path} refused the request ({e.code}: {detail})") from None
                last = f"{e.code}: {detail}"
            except (urllib.error.URLError, OSError, TimeoutError, http.client.HTTPException) as e:
                last = _one_line(str(getattr(e, "reason", e))) or type(e).__name__  # HTTPException: no HTTP answer
            except ValueError as e:
                raise EndpointError(f"{base + path} answered what is not JSON ({e})") from None
            if attempt < self.retries:
                time.sleep(self.backoff * 2 ** attempt)
        raise EndpointError(f"{base + path} failed {self.retries + 1} times (last: {last}): check the server; what "
                            "it had not answered was not written to the cache")


# --- the served model's identity and the probes --------------------------------------------------
def served_fingerprint(spec: str) -> dict:
    """The served model's fingerprint, with its "embedding_dim" (None: the local sentence model
    embeds); memoised per process, as it asks the server and probes the engine."""
    if spec not in _FINGERPRINTS:
        model, url, key = parse_spec(spec)
        client = Client(url, key, timeout=20.0, retries=1)
        try:
            models, headers = client.call("/models")
        except EndpointError as e:
            raise EngineUnreachableError(f"no OpenAI-compatible server answers at {url} ({e}): start one (docs/scale.md: "
                                         "serving Llama-3-8B with vLLM) or check --endpoint") from None
        served = [m.get("id") for m in _listed(models)]
        if model not in served:
            raise UsageError(f"the server at {url} serves {', '.join(map(str, served)) or 'no model'}, not {model!r}: "
                             "pass --model as it names it")
        try:
            version, _ = client.call("/version", root=True)
            engine = f"version {str(version.get('version', '?'))[:80]}"
        except EndpointError:
            engine = f"server {headers['server'][:80]}" if headers.get("server") else "unknown"
        pooled = embed_url(spec)
        dim, pooling = _embedding_endpoint(Client(pooled, key, timeout=60.0, retries=1) if pooled else client, model,
                                           models, required=pooled is not None)
        probe = _probe_engine(Client(url, key, timeout=60.0, retries=0), model)
        _ENGINES[spec] = probe
        if not probe.batches:
            engine += "; one prompt per request"
            log.info("the engine at %s (%s) takes one prompt per request: illm sends them one at a time, "
                     "--concurrency at a time", url, engine.split(";")[0])
        if dim:
            embedder = f"endpoint /v1/embeddings ({dim})" if not pooled else f"pooling endpoint, {pooling} ({dim})"
        else:
            from illm_tools.llm.sentence import embedder_id

            embedder = f"{embedder_id()} (local: the endpoint has no embeddings)"
        _FINGERPRINTS[spec] = {"model_id": model, "source": "openai", "engine": engine, "sha256": None,
                               "revision": None, "embedder": embedder, "embedding_dim": dim, "dtype": "served",
                               "quant": "served"}
    return dict(_FINGERPRINTS[spec])


def _listed(models: dict) -> list[dict]:
    """The served models a `GET /v1/models` answer lists (its `data`'s objects; anything else: none)."""
    data = models.get("data")
    return [m for m in data if isinstance(m, dict)] if isinstance(data, list) else []


def engine_probe(spec: str) -> EngineProbe:
    """What the connection probes found of the engine serving `spec` (probing it on first use)."""
    served_fingerprint(spec)
    return _ENGINES[spec]


def forget_engines() -> None:
    """Forget what this process asked the engines, so that the next use asks afresh."""
    _FINGERPRINTS.clear()
    _ENGINES.clear()


def check_ranking(spec: str) -> None:
    """Raise `EndpointError` (one line) unless the engine serving `spec` passed the alignment probe."""
    engine = served_fingerprint(spec)["engine"]  # probes the engine on first use
    probe = _ENGINES[spec]
    if probe.aligned:
        return
    what = ("its prompt log-probabilities are not those of its own generation (as if shifted by one position)"
            if probe.aligned is False else "it cannot score prompt tokens")
    raise EndpointError(f"the engine at {parse_spec(spec)[1]} ({engine}) cannot rank actions: "
                        f"{what}: {probe.detail}; rank with vLLM or --backend transformers, or pass --tasks summary to "
                        "write only summaries through this engine; nothing was annotated")


def _embedding_endpoint(client: Client, model: str, served: dict, *, required: bool) -> tuple[int | None, str]:
    """(dimension, description) of the texts' embeddings from `client`'s `/v1/embeddings` for `model`,
    or (None, "") where it has none and none was asked for. A pooling endpoint given with
    --embed-endpoint must serve the same weights as the completions endpoint: where both say what
    they serve (vLLM's `root`, the weights' folder or hub id) the two must agree."""
    where = client.url
    try:
        answer, _ = client.call("/embeddings", {"model": model, "input": ["probe"]})
        embedding = answer["data"][0]["embedding"]
        if not isinstance(embedding, list):
            raise TypeError("the embedding is not a list of numbers")
        dim = len(embedding)
    except (EndpointError, KeyError, IndexError, TypeError) as e:
        if not required:
            return None, ""
        raise UsageError(f"the pooling endpoint {where} gives no embeddings of {model!r} ({e}): start the same weights "
                         "with vLLM's pooling runner (docs/scale.md) or leave --embed-endpoint out") from None
    if not required:
        return dim, ""
    try:
        pooled_models, _ = client.call("/models")
        version, _ = client.call("/version", root=True)
    except EndpointError:
        pooled_models, version = {}, {}
    roots = {m.get("id"): m.get("root") for m in _listed(pooled_models)}
    mine = {m.get("id"): m.get("root") for m in _listed(served)}
    if roots.get(model) and mine.get(model) and roots[model] != mine[model]:
        raise UsageError(f"the pooling endpoint {where} serves {roots[model]} as {model!r}, the completions endpoint "
                         f"{mine[model]}: embeddings must come from the same weights; start both on one model")
    return dim, f"{str(roots.get(model) or model)[:200]}, engine {str(version.get('version', '?'))[:80]}"


def _probe_engine(client: Client, model: str) -> EngineProbe:
    """Ask the engine once: does it take a list of prompts; are its echoed prompt log-probs those its
    generation gives (see the module docstring)? Log-probs that are not numbers answer no."""
    try:
        return _probe(client, model)
    except (ValueError, TypeError, AttributeError, OverflowError):  # a top list, a log-prob that is no number
        return EngineProbe(False, None, "its log-probabilities are not numbers")


def _probe(client: Client, model: str) -> EngineProbe:
    try:
        answer, _ = client.call("/completions", {"model": model, "prompt": ["One,", "Two,"], "max_tokens": 1,
                                                 "temperature": 0})
        batches = len(answer.get("choices", [])) == 2
    except EndpointError:
        batches = False
    detail = "its echo never scored one of the likely next tokens as one token after the context"
    for context in ALIGNMENT_CONTEXTS:
        try:
            generated, _ = client.call("/completions", {"model": model, "prompt": context, "max_tokens": 1,
                                                        "temperature": 0, "logprobs": ALIGNMENT_TOP})
            lp = generated["choices"][0]["logprobs"]
            top = (lp.get("top_logprobs") or [None])[0] or {lp["tokens"][0]: lp["token_logprobs"][0]}
        except (EndpointError, KeyError, IndexError, TypeError, AttributeError):
            return EngineProbe(batches, None, "it gives no log-probabilities with its completions")
        for token, generated_lp in sorted(top.items(), key=lambda kv: -float(kv[1])):
            if not token.strip() or "\ufffd" in token:  # a byte of a character: its text is not the token
                continue
            text = context + token
            try:
                echoed, _ = client.call("/completions", {"model": model, "prompt": text, "max_tokens": 1,
                                                         "temperature": 0, "echo": True, "logprobs": 1})
                lp = echoed["choices"][0]["logprobs"]
                scored = [(o, v) for o, v in zip(lp["text_offset"], lp["token_logprobs"]) if o < len(text)]
            except (EndpointError, KeyError, IndexError, TypeError):
                return EngineProbe(batches, None, "it gives no prompt log-probabilities (echo with logprobs)")
            after = [v for o, v in scored if o >= len(context)]
            if len(after) != 1 or after[0] is None or len(context) not in [o for o, _ in scored]:
                continue  # the token is not one token once scored with the context: the next likely one
            echo_lp = float(after[0])
            detail = (f"the token {token!r} after {context!r} has log-prob {float(generated_lp):.2f} when generated and "
                      f"{echo_lp:.2f} when scored with echo")
            return EngineProbe(batches, abs(echo_lp - float(generated_lp)) <= ALIGNMENT_TOLERANCE, detail)
    return EngineProbe(batches, None, detail)
