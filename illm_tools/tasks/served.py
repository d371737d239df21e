"""A cache's served models (a backend's model only its engine can fingerprint: openai's), read from its
rows without asking the engine, through the hooks of its backend's class (`identity`, `served_as`,
`address_of`, `reached_model`; a backend without them serves no such model): how an adopted served model is reached (`REACHED`, `reached_model`: by the
user's own --endpoint, --api-key-env and --embed-endpoint only; a row's spec is an identity, never an
address to contact), the options that select a held setup with the address left for the user
(`held_options`), the addresses its rows were annotated at (`served_addresses`, a record only), and the
model's fingerprint read from the rows of the same served model when its engine is stopped
(`cached_identity`, `model_identity`). `illm_tools.tasks.annotation_setup` lists and adopts a cache's setups with
these."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from illm_tools.errors import UsageError
from illm_tools.llm.backend import backend_class

REACHED = ("endpoint", "api_key_env", "embed_endpoint")
"""The `LLMSpec` options that say where a served model is reached and which variable holds its key:
the user's own only, never adopted from a cache (`reached_model`)."""


def reached_model(backend: str, model: str, reach: Mapping[str, str | None], where) -> dict:
    """The `LLMSpec` fields naming an adopted model: `model` and `reach` (the user's own --endpoint,
    --api-key-env and --embed-endpoint; None or absent where not given). A served model (openai) is
    its served name alone, reached where `reach` says: the address and key variable of the spec its
    rows were written under (`model`) are never read, and without --endpoint it is refused in one line
    naming the options to give (`where`: the cache). Another backend's model is kept, with `reach` as
    given (which `LLMSpec` refuses in one line: those options are the openai backend's)."""
    given = {k: reach[k] for k in REACHED if reach.get(k)}
    reached = getattr(backend_class(backend), "reached_model", None)
    return {"model": model, **given} if reached is None else {**reached(model, given, where), **given}


def held_options(backend: str, model: str, dtype: str, quant: str) -> str:
    """The options that select a held model setup (`selecting_options`), a served model's address
    left for the user to give (`--endpoint URL`): a cache's rows never suggest where a request goes."""
    from illm_tools.llm.backend import selecting_options

    identity = getattr(backend_class(backend), "identity", None)  # as a shared file names a served model
    return selecting_options(backend, identity(model) if identity is not None else model, dtype, quant)


def served_addresses(specs: Sequence[str]) -> list[str]:
    """The engine URLs of served model specs (openai's "NAME@URL"), in order; [] for other models and
    for a shared file's address-free identities ("openai:NAME")."""
    from illm_tools.llm.backend import BACKENDS

    readers = [cls.address_of for name in BACKENDS if hasattr(cls := backend_class(name), "address_of")]
    return [url for m in specs for address_of in readers if (url := address_of(m)) is not None]


def cached_identity(cache, backend: str, model: str) -> tuple[str, int | None] | None:
    """For a model only its engine can fingerprint (openai): the fingerprint hash and embedding width
    the cache's rows carry for the same served model at any address (its backend's `served_as`),
    when they carry one; None when they carry none; several are refused in one line. A run that
    cannot reach the engine reads its keys from these, so training from the cache asks it nothing."""
    from illm_tools.cache.store import AnnotationCache

    root = cache.root if isinstance(cache, AnnotationCache) else cache
    served_as = getattr(backend_class(backend), "served_as", None)
    if served_as is None or root is None or not (Path(root) / "manifest.json").is_file():
        return None
    cache = cache if isinstance(cache, AnnotationCache) else AnnotationCache(cache)
    rows = cache.setups()
    want = served_as(model)
    found: dict[str, set] = {}
    for row in rows:
        try:
            same = served_as(row["model"]) == want
        except UsageError:  # a row of another backend
            continue
        if same:
            found.setdefault(row["model_fingerprint"], set())
    if not found:
        return None
    if len(found) > 1:
        raise UsageError(f"the cache {cache.root} holds rows of {want[0]} with {len(found)} model identities (other "
                         "weights or engines behind its address): start the engine, whose answers say which is "
                         "this run's")
    fingerprint = next(iter(found))
    table = cache.table(["model_fingerprint", "embedding_dim"])
    dims = {d for f, d in zip(table.column("model_fingerprint").to_pylist(), table.column("embedding_dim").to_pylist())
            if f == fingerprint and d is not None}
    return fingerprint, (dims.pop() if len(dims) == 1 else None)


def model_identity(llm, cache) -> tuple[str, str | None]:
    """(the fingerprint hash of an `LLMSpec`'s model, None or why its engine does not answer). Asked
    of the backend (no weights loaded); where only an engine can tell (openai) and none answers, read
    from the rows of the same served model in `cache` (`cached_identity`): a run trains from the
    cache with the engine stopped, under any address it was annotated at. Neither: one line."""
    from illm_tools.errors import EngineUnreachableError

    try:
        return llm.fingerprint(), None
    except EngineUnreachableError as e:
        unreachable = str(e).split(" (")[0]  # "no OpenAI-compatible server answers at URL"
    found = cached_identity(cache, llm.backend, llm.model)
    if found is None:
        raise UsageError(f"{unreachable}: start it, or train from a cache that holds this model's annotations "
                         f"({cache.root} holds none)")
    return found[0], unreachable
