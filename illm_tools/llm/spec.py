"""The LLM of a stage as one value: which backend serves which model, in what dtype and
quantisation, on which device. `illm annotate`, `illm serve`, `illm probe` and a training run's
live fallback each hold one (`config.llm`); its `fingerprint()` is what every cache key of the
model carries, and `options()` the flags that select it, so the model's identity is built in one
place instead of from loose fields in each stage.

How a model is named is folded into `model` when the spec is made (`resolve_model`): the backend's
default when none is given, the oracle's noise ("oracle:noise=0.5"), an OpenAI-compatible
server's endpoint ("NAME@URL#VAR"). Two specs naming the same model the two ways are equal.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from illm_tools.errors import UsageError
from illm_tools.settings import setting


@dataclass(frozen=True)
class LLMSpec:
    """The LLM a stage loads (see the module docstring)."""

    backend: str = setting("transformers", adopted=True)
    """LLM backend: transformers | oracle (rule-based annotators that know BabyAI/MiniGrid, MiniHack and
    Crafter: the positive control) | openai (an OpenAI-compatible server: vLLM, ...; with --endpoint) | stub (deterministic
    answers from the prompt, no weights; for tests)."""
    model: str | None = setting(None, adopted=True)
    """Alias (see `illm models`), hub id or local folder; default: the backend's (smollm2-135m for
    transformers, oracle for oracle)."""
    dtype: str = setting("auto", flag="--dtype", adopted=True, auto=True, flat="model_dtype")
    """Compute dtype: auto | bfloat16 | float32 | float16; auto: bfloat16 on CUDA, and on a CPU where a
    timed matmul says it is faster than float32, else float32 (measured once per machine). The resolved
    dtype is part of every cache key."""
    quant: str = setting("auto", adopted=True, auto=True)
    """bitsandbytes quantisation: none | 4bit (NF4) | 8bit | auto (on a CUDA device what the model's alias
    says: 4bit for llama3 and llama2, as the paper ran its annotator; else none). The resolved value is
    part of every cache key."""
    device: str | None = setting(None, resumes=True, machine=True, flat="llm_device")
    """Where the model runs: cpu | cuda | cuda:N | auto (a GPU where torch sees one, else the CPU; with
    several processes each takes its own GPU); unset: auto (a training run's: its --device)."""
    oracle_noise: float = setting(0.0, adopted=True)
    """oracle: the share of states (fixed, keyed by the state) answered at random; 1 is an annotator
    that knows nothing (part of every key)."""
    endpoint: str | None = None
    """openai: the server's OpenAI base URL, e.g. http://127.0.0.1:8000/v1 (--model is the model as it
    serves it)."""
    api_key_env: str | None = None
    """openai: the environment variable holding the server's API key (default OPENAI_API_KEY)."""
    embed_endpoint: str | None = None
    """openai: the OpenAI base URL of a pooling server of the same weights (vLLM `--runner pooling`)
    that embeds the summaries; unset: the endpoint's own /v1/embeddings, else a local sentence model."""
    offline: bool = setting(False, compare=False, run_setting=False)
    """Never download a hub model: use only what is in the Hugging Face cache (as HF_HUB_OFFLINE=1)."""
    batch_tokens: int | None = setting(None, compare=False, run_setting=False)
    """transformers: tokens one engine batch may hold (its states' prompts, packed candidates and summary
    tokens; --batch-size stays the most states); default: a quarter of the memory free when the model
    loads (RAM on a CPU, device memory on CUDA) over what a token holds."""

    def __post_init__(self) -> None:
        from illm_tools.devices import check_device
        from illm_tools.llm.backend import check_backend, resolve_model
        from illm_tools.llm.dtype import CHOICES
        from illm_tools.llm.loading import QUANTS

        check_backend(self.backend)
        if self.dtype not in CHOICES:
            raise UsageError(f"--dtype must be one of {', '.join(CHOICES)}, got {self.dtype!r}")
        if self.quant not in (*QUANTS, "auto"):
            raise UsageError(f"--quant must be one of {', '.join(QUANTS)} or auto, got {self.quant!r}")
        if self.device is not None:
            check_device(self.device)
        from illm_tools.settings import check_numbers

        check_numbers(self, positive=("batch_tokens",))
        if not 0.0 <= self.oracle_noise <= 1.0:
            raise UsageError(f"--oracle-noise must be between 0 and 1, got {self.oracle_noise}")
        model = resolve_model(self.backend, self.model, oracle_noise=self.oracle_noise, endpoint=self.endpoint,
                              api_key_env=self.api_key_env, embed_endpoint=self.embed_endpoint)
        for name, value in (("model", model), ("oracle_noise", 0.0), ("endpoint", None), ("api_key_env", None),
                            ("embed_endpoint", None)):
            object.__setattr__(self, name, value)

    def placed(self, state=None) -> LLMSpec:
        """This spec with the machine's choices made: the device (auto -> cuda or cpu; under
        accelerate's `state`, this process's own), the dtype (auto -> what `illm_tools.llm.dtype`
        measures on that device; the oracle: float32) and the quantisation (auto -> the model's
        alias on CUDA, else none: `backend_quant`)."""
        from illm_tools.devices import resolve_device
        from illm_tools.llm.backend import backend_dtype, backend_quant

        device = resolve_device(self.device or "auto", state)
        return dataclasses.replace(self, device=device, dtype=backend_dtype(self.backend, self.dtype, device),
                                   quant=backend_quant(self.backend, self.model, self.quant, device))

    def _concrete(self) -> LLMSpec:
        """Placed unless already placed (fingerprints and loads need the resolved values)."""
        return self if not {"auto", None} & {self.device, self.dtype, self.quant} else self.placed()

    def _downloads(self):
        """No hub downloads under --offline (`illm_tools.llm.hub.no_downloads`)."""
        import contextlib

        from illm_tools.llm import hub

        return hub.no_downloads("--offline was given") if self.offline else contextlib.nullcontext()

    def fingerprint(self) -> str:
        """The hash every cache key of this model carries (without loading weights; a hub model
        missing from the cache is downloaded first where the machine is online)."""
        from illm_tools.keys import fingerprint_hash
        from illm_tools.llm.backend import backend_fingerprint

        spec = self._concrete()
        with self._downloads():
            return fingerprint_hash(backend_fingerprint(spec.backend, spec.model, dtype=spec.dtype, quant=spec.quant))

    def hidden_size(self) -> int:
        """The model's hidden size (the summary embedding's width), without loading weights."""
        from illm_tools.llm.backend import backend_hidden_size

        return backend_hidden_size(self.backend, self.model)

    def load(self, cache_dir: str | None = None):
        """The loaded backend (`illm_tools.llm.backend.load_backend`)."""
        from illm_tools.llm.backend import load_backend

        spec = self._concrete()
        with self._downloads():
            return load_backend(spec.backend, spec.model, dtype=spec.dtype, quant=spec.quant, device=spec.device,
                                cache_dir=cache_dir, batch_tokens=self.batch_tokens)

    def preload(self, cache_dir: str | None = None) -> None:
        """Import what `load` will, reading no weights, downloading nothing and measuring nothing
        (the device and dtype need not be placed yet: `illm_tools.llm.backend.preload_backend`); a
        hub model not here yet is left to `load`, under the run's own download settings."""
        from illm_tools.llm import hub
        from illm_tools.llm.backend import preload_backend

        with hub.no_downloads("a preload downloads nothing"):
            preload_backend(self.backend, self.model, cache_dir=cache_dir)

    def check_use(self, env_id: str, renderer: str) -> None:
        """Refuse in one line an env (or hop states) the backend cannot read (the oracle: hop)."""
        from illm_tools.llm.backend import check_backend_use

        check_backend_use(self.backend, env_id, renderer)

    def check_ranking(self) -> None:
        """Refuse in one line a ranking task the backend cannot answer with this model (the openai
        backend: an engine whose echoed log-probs fail its alignment probe)."""
        from illm_tools.llm.backend import backend_class

        check = getattr(backend_class(self.backend), "check_ranking", None)
        if check is not None:
            check(self.model)

    def options(self) -> str:
        """The flags that select this model ("--model smollm2-135m --dtype bfloat16 --quant none",
        "--backend oracle --oracle-noise 0.5"; `selecting_options`)."""
        from illm_tools.llm.backend import selecting_options

        return selecting_options(self.backend, self.model, self.dtype, self.quant)
