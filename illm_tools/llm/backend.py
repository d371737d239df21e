"""The LLM backend protocol: everything the annotation engine, the live fallback and iLLM(hop) ask
of a language model, and the registry that names the implementations.

A backend knows its model's `fingerprint` (what every cache key hashes), `hidden_size` (the
summary embedding's width) and `device`, and answers:

- `score(contexts, candidates)`: log P(candidate | context) per candidate (`CandidateScores`);
- `generate(prompts, max_new_tokens)`: greedy continuations with their embeddings (`Generation`);
- `score_and_generate(...)`: both tasks of each state (a backend may share their prompt prefix);
- `embed(texts)`: [n, hidden] text embeddings;
- iLLM(hop), prompts with input embeddings spliced in: `input_embeddings()` (the [V, d] matrix the
  Hopfield translation reads), `last_hidden(windows)` (Z_h: the state after reading each window of
  input embeddings) and `spliced(items, ...)` (action scores and summaries of prompts whose history
  is a window of input embeddings, `SplicedPrompt`).

`BACKENDS` maps a name to "module:Class"; `load_backend(name, model, ...)` builds one (an unknown
name is refused in one line), `backend_fingerprint` / `backend_hidden_size` answer without loading
weights. `transformers` (the default: `illm_tools.llm.transformers_backend`) runs real models;
`stub` (`illm_tools.llm.stub`) answers deterministically from the prompt, for tests and
benchmarks of everything around the LLM; `oracle` (`illm_tools.llm.oracle`) answers the prompts
of every game an oracle knows (`illm_tools.oracles`, one per suite: BabyAI and MiniGrid, MiniHack, Crafter) as a
player who knows the game, the positive control. Another backend is one new file plus one entry here.

Optional, on a backend class: `default_model` (the model when none is named: `resolve_model`),
`model_options` and `model_spec(model, **options)` (options folded into its model spec, e.g. the oracle's
noise: `resolve_model`; a spec given as `model` is returned as it is), `selecting_options(model)` (the options that select such a spec:
`selecting_options`), `quantises` (`--quant auto` picks the alias's 4-bit on CUDA: `backend_quant`),
`setting_of(model)` (a setting its spec holds, as reports name it: `rl.compare`), `local_models`
(its models are this machine's files, which a dry run checks: `experiment.plan`),
`check_use(env_id, renderer)` (refuse, in one line, envs or hop states it cannot read:
`check_backend_use`) and `preload(model, cache_dir=)` (import what its `load` will, reading no
weights: `preload_backend`, for a live worker started before its run is configured).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from illm_tools.errors import UsageError
from illm_tools.llm.spliced import SplicedPrompt
from illm_tools.registry import Registry

def _backend_problem(cls) -> str | None:
    """What keeps a class from being a backend: the class methods loading calls."""
    if not isinstance(cls, type):
        return "is not a class"
    missing = [m for m in ("load", "model_fingerprint", "model_hidden_size") if not callable(getattr(cls, m, None))]
    return f"has no {', '.join(missing)} (see the Backend protocol)" if missing else None


BACKENDS: Registry = Registry("LLM backend", "illm.backends", check=_backend_problem, hint="--backend")
"""Backend name -> its class ("module:Class", imported on first use, or the class); installed
packages add theirs through `illm.backends` entry points."""
BACKENDS.register("transformers", "illm_tools.llm.transformers_backend:TransformersBackend")
BACKENDS.register("stub", "illm_tools.llm.stub:StubBackend")
BACKENDS.register("oracle", "illm_tools.llm.oracle:OracleBackend")
BACKENDS.register("openai", "illm_tools.llm.openai:OpenAIBackend")
DEFAULT_BACKEND = "transformers"


@runtime_checkable
class Backend(Protocol):
    name: str
    model: str
    fingerprint: dict
    hidden_size: int
    device: str

    def score(self, contexts: Sequence[str], candidates: Sequence[Sequence[str]], *, batch_size: int = 8) -> list: ...

    def generate(self, prompts: Sequence[str], *, max_new_tokens: int = 64, batch_size: int = 8) -> list: ...

    def score_and_generate(self, contexts: Sequence[str], candidates: Sequence[Sequence[str]],
                           prompts: Sequence[str], *, max_new_tokens: int = 64,
                           batch_size: int = 8) -> tuple[list, list]: ...

    def embed(self, texts: Sequence[str], *, batch_size: int = 8) -> Any: ...

    def input_embeddings(self) -> Any: ...

    def last_hidden(self, windows: Sequence[Any]) -> Any: ...

    def spliced(self, prompts: Sequence[SplicedPrompt], *, max_new_tokens: int = 64,
                batch_size: int = 8) -> list: ...


def check_backend(name: str) -> None:
    """Refuse an unknown backend name in one line (nothing is imported)."""
    if name not in BACKENDS:
        raise UsageError(BACKENDS.unknown(name))


def backend_class(name: str) -> type:
    """The class registered as `name`; an unknown name is refused in one line."""
    return BACKENDS.load(name)


MODEL_OPTIONS = ("oracle_noise", "endpoint", "api_key_env", "embed_endpoint")
"""The options a backend may fold into its model spec (a class's `model_options` names its own)."""


def resolve_model(backend: str, model: str | None, *, oracle_noise: float = 0.0, endpoint: str | None = None,
                  api_key_env: str | None = None, embed_endpoint: str | None = None) -> str:
    """The model spec a backend serves: its class's `model_spec(model, **its options)` where it folds
    options into the spec (the oracle's `--oracle-noise`: "oracle:noise=0.5"; an endpoint's URL and key
    variable: "NAME@URL#VAR"), else `model` or the backend's default when None (smollm2-135m for
    transformers). An option of another backend is refused in one line naming it."""
    cls = backend_class(backend)
    given = {"oracle_noise": oracle_noise, "endpoint": endpoint, "api_key_env": api_key_env,
             "embed_endpoint": embed_endpoint}
    takes = getattr(cls, "model_options", ())
    foreign = [k for k in MODEL_OPTIONS if given[k] and k not in takes]
    if foreign:
        owner = next(n for n in BACKENDS if foreign[0] in getattr(backend_class(n), "model_options", ()))
        flags = ", ".join("--" + k.replace("_", "-") for k in foreign)
        raise UsageError(f"{flags} {'is' if len(foreign) == 1 else 'are'} the {owner} backend's: add --backend "
                         f"{owner} (this command uses --backend {backend})")
    if hasattr(cls, "model_spec"):
        return cls.model_spec(model, **{k: given[k] for k in takes})
    if model is not None:
        return model
    from illm_tools.llm.registry import DEFAULT_MODEL

    return getattr(cls, "default_model", DEFAULT_MODEL)


def backend_dtype(backend: str, dtype: str, device: str = "cpu") -> str:
    """The concrete compute dtype of a backend's model (`illm_tools.llm.dtype.resolve_dtype`); a
    backend without one (`computes = False`: the oracle) takes float32 and measures nothing."""
    from illm_tools.llm.dtype import resolve_dtype

    if not getattr(backend_class(backend), "computes", True):
        resolve_dtype(dtype if dtype != "auto" else "float32")  # still refuses a dtype that is no dtype
        return "float32"
    return resolve_dtype(dtype, device)


def backend_quant(backend: str, model: str, quant: str, device: str = "cpu") -> str:
    """The concrete quantisation: `quant`, or for auto what the model's alias asks on a CUDA device
    (`ModelSpec.gpu_quant`: 4bit for llama3/llama2, as the paper ran its annotator) and none elsewhere
    (on a CPU bfloat16 or float32 is faster than bitsandbytes' 4-bit kernels) or for a backend that
    computes nothing here (no `quantises` on its class)."""
    if quant != "auto":
        return quant
    if not getattr(backend_class(backend), "quantises", False) or not str(device).startswith("cuda"):
        return "none"
    from illm_tools.errors import ModelNotFoundError
    from illm_tools.llm.registry import resolve

    try:
        return resolve(model).gpu_quant
    except ModelNotFoundError:
        return "none"


def check_backend_use(backend: str, env_id: str, renderer: str) -> None:
    """Refuse in one line an env (or hop states: a renderer "hop@...") the backend cannot read."""
    check = getattr(backend_class(backend), "check_use", None)
    if check is not None:
        check(env_id, renderer)


def describe_model(model: str, fingerprint: str) -> dict | None:
    """{"backend", "model", "dtype", "quant"} whose fingerprint hash is `fingerprint` (what a cache
    row stores with its `model`), or None when no backend here reproduces it (another revision or
    file, or a model not available on this machine). A backend whose fingerprint only its engine
    knows (`describe_offline`: openai) describes its rows from their model spec, trusting the
    row's hash: nothing is contacted."""
    from illm_tools.keys import fingerprint_hash
    from illm_tools.llm.hub import no_downloads

    for name in BACKENDS:  # a backend only its engine can fingerprint describes its rows from the spec
        offline = getattr(backend_class(name), "describe_offline", None)
        found = offline(model) if offline is not None else None
        if found is not None:
            return found
    with no_downloads():  # a row's model is described from what is here, never fetched
        for name in BACKENDS:
            cls = backend_class(name)
            if getattr(cls, "describe_offline", None) is not None:
                continue
            for dtype in ("bfloat16", "float32", "float16"):
                for quant in ("none", "4bit", "8bit"):
                    try:
                        if fingerprint_hash(cls.model_fingerprint(model, dtype=dtype, quant=quant)) == fingerprint:
                            return {"backend": name, "model": model, "dtype": dtype, "quant": quant}
                    except Exception:  # noqa: BLE001 - not a model this backend serves (or not here)
                        break
    return None


def model_options(model: str, fingerprint: str) -> str:
    """The options that select the model of a cache row (its `model` and fingerprint hash), as
    `selecting_options` writes them, or the model alone, said to be another file or revision, when
    no backend here reproduces the fingerprint."""
    found = describe_model(model, fingerprint)
    if found is None:
        return f"--model {model} (another file or revision)"
    return selecting_options(**found)


def selecting_options(backend: str, model: str, dtype: str, quant: str) -> str:
    """The options that select a model setup: "--backend oracle --oracle-noise 0.5", "--backend
    stub --model stub:64 --dtype float32 --quant none", "--model smollm2-135m --dtype bfloat16
    --quant none", "--backend openai --model NAME --endpoint URL"."""
    options = getattr(backend_class(backend), "selecting_options", None)
    if options is not None:  # a backend whose model spec holds its options (the oracle's noise, an engine's address)
        return options(model)
    prefix = "" if backend == DEFAULT_BACKEND else f"--backend {backend} "
    return f"{prefix}--model {model} --dtype {dtype} --quant {quant}"


def load_backend(name: str, model: str, *, dtype: str = "auto", quant: str = "none", device: str = "cpu",
                 cache_dir: str | None = None, batch_tokens: int | None = None):
    """The backend `name` serving `model` (an alias, hub id or folder for transformers), computing in
    `dtype` ("auto": `backend_dtype`, as the commands resolve it); `batch_tokens` (given only when
    set: a plug-in backend need not take it) bounds an engine batch (`illm_tools.llm.budget`)."""
    engine = {"batch_tokens": batch_tokens} if batch_tokens is not None else {}
    return backend_class(name).load(model, dtype=backend_dtype(name, dtype, device), quant=quant, device=device,
                                    cache_dir=cache_dir, **engine)


def preload_backend(name: str, model: str, *, cache_dir: str | None = None) -> None:
    """Import what `load_backend(name, model)` will, reading no weights (the backend's optional
    `preload`; a backend without one has nothing worth doing ahead)."""
    preload = getattr(backend_class(name), "preload", None)
    if preload is not None:
        preload(model, cache_dir=cache_dir)


def backend_fingerprint(name: str, model: str, *, dtype: str = "auto", quant: str = "none") -> dict:
    """What `load_backend(...).fingerprint` will be, without loading weights."""
    return backend_class(name).model_fingerprint(model, dtype=backend_dtype(name, dtype), quant=quant)


def backend_hidden_size(name: str, model: str) -> int:
    """The model's hidden size (the summary embedding's width), without loading weights."""
    return backend_class(name).model_hidden_size(model)


def as_backend(lm):
    """A backend for `lm`: itself, or a loaded transformers model (`LoadedModel`) wrapped by the
    backend registered as transformers."""
    if isinstance(lm, Backend):
        return lm
    return backend_class(DEFAULT_BACKEND)(lm)
