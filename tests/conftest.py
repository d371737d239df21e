"""Shared test fixtures: tiny random causal LMs with a tiny trained BPE tokenizer (offline, built
once per session in well under a second), BabyAI-like prompts, and the plain reference scorer
that the one scoring path is checked against."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
# `--dtype auto` and the heads' bf16 choice as on a machine where float32 is the faster: the same
# answer on every CPU kind (an AVX2-only CPU runs bf16 30x slower), and no probe line in outputs.
# tests/test_machine_choices.py measures the real probe and simulates both answers.
os.environ.setdefault("ILLM_DTYPE_PROBE", "float32")
# The tests' fake hubs (tests/fakes/ `fake_hub`) answer from a thread of the test's own process: on a
# loaded machine one answer took over the hub client's 10 s default (a ReadTimeout under a CPU hog).
# A generous per-request timeout, set before huggingface_hub reads it, keeps the verdict off the speed.
os.environ.setdefault("HF_HUB_ETAG_TIMEOUT", "300")
os.environ.setdefault("HF_HUB_DOWNLOAD_TIMEOUT", "300")

ACTIONS = ["turn left", "turn right", "go forward", "pick up", "drop", "toggle"]
_CORPUS = [
    "You are an expert player playing BabyAI. Your goal is to go to the red ball.",
    "Valid actions: turn left, turn right, go forward, pick up, drop, toggle",
    "Observation 0: You see a wall 2 steps forward, a red ball 1 step left and 3 steps forward.",
    "Action 0: go forward. Observation 1: You see a grey key 2 steps right, a blue box 1 step left.",
    "Suggest the best action the player can take. What do you do? Summarize the main points.",
] * 3


def babyai_context(step: int) -> str:
    """A BabyAI-Text style prompt; `step` varies its length and content."""
    history = "".join(
        f"Observation {i}: You see a wall {i + 2} steps forward, a red ball {i % 3 + 1} step left.\n"
        f"Action {i}: {ACTIONS[(i + step) % len(ACTIONS)]}\n" for i in range(step % 3 + 1))
    return ("You are an expert player playing BabyAI. Your goal is to go to the red ball.\n"
            f"Valid actions: {', '.join(ACTIONS)}\nYou see: {history}"
            "Suggest the best action the player can take. What do you do?\nAction:")


def _train_tokenizer(folder, *, add_bos: bool):
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors, trainers
    from transformers import PreTrainedTokenizerFast

    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(vocab_size=400, special_tokens=["<eos>", "<bos>"],
                                  initial_alphabet=pre_tokenizers.ByteLevel.alphabet(), show_progress=False)
    tok.train_from_iterator(_CORPUS, trainer)
    if add_bos:
        tok.post_processor = processors.TemplateProcessing(single="<bos> $A", special_tokens=[("<bos>", 1)])
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, eos_token="<eos>", bos_token="<bos>")
    fast.save_pretrained(folder)
    return fast


def _tiny_model(folder, vocab: int, kind: str, layers: int = 2) -> None:
    import torch
    from transformers import AutoModelForCausalLM, Gemma3TextConfig, GPT2Config, LlamaConfig

    torch.manual_seed(0)
    common = dict(vocab_size=vocab, hidden_size=64, intermediate_size=128, num_hidden_layers=layers,
                  num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=1024,
                  bos_token_id=1, eos_token_id=0, pad_token_id=None, tie_word_embeddings=True)
    if kind == "sliding":
        config = Gemma3TextConfig(**common, head_dim=16, sliding_window=8,
                                  layer_types=["sliding_attention", "full_attention"])
    elif kind == "gpt2":  # learned absolute positions, fused attention projections, no key-value heads
        config = GPT2Config(vocab_size=vocab, n_embd=64, n_layer=layers, n_head=4, n_positions=1024,
                            bos_token_id=1, eos_token_id=0, tie_word_embeddings=True)
    else:
        config = LlamaConfig(**common)
    model = AutoModelForCausalLM.from_config(config)
    with torch.no_grad():  # larger weights than the default init, so log-probs differ visibly
        for p in model.parameters():
            p.mul_(8.0) if p.dim() > 1 else None
    model.save_pretrained(folder)


def _build(tmp_path_factory, name: str, *, add_bos: bool = False, kind: str = "llama"):
    from illm_tools.llm.loading import load_model

    folder = tmp_path_factory.mktemp(name)
    tok = _train_tokenizer(folder, add_bos=add_bos)
    _tiny_model(folder, len(tok), kind)
    return load_model(str(folder), dtype="float32", cache_dir=tmp_path_factory.mktemp(f"{name}-cache"))


@pytest.fixture(scope="session")
def tiny_lm(tmp_path_factory):
    """Tiny random Llama, tokenizer without BOS (like SmolLM2)."""
    return _build(tmp_path_factory, "tiny-llama")


@pytest.fixture(scope="session")
def tiny_lm_bos(tmp_path_factory):
    """Tiny random Llama whose tokenizer prepends <bos> (like Gemma)."""
    return _build(tmp_path_factory, "tiny-llama-bos", add_bos=True)


@pytest.fixture(scope="session")
def tiny_lm_gpt2(tmp_path_factory):
    """Tiny random GPT-2 (the registry's `gpt2` family)."""
    return _build(tmp_path_factory, "tiny-gpt2", kind="gpt2")


@pytest.fixture(scope="session")
def tiny_lm_sliding(tmp_path_factory):
    """Tiny random Gemma-3 text model with an 8-token sliding window on one layer."""
    return _build(tmp_path_factory, "tiny-gemma3", add_bos=True, kind="sliding")


def _dequantise_smollm2(root) -> None:
    from illm_tools.llm.loading import load_model

    load_model("smollm2-135m", dtype="float32", cache_dir=root)  # de-quantised, each file's hash memoised


@pytest.fixture(scope="session")
def smollm2_cache(tmp_path_factory):
    """An illm cache folder (`cache_dir=`, ILLM_CACHE_DIR) holding the real embedded model, SmolLM2-135M,
    de-quantised once per test run (about 20 s) by the first worker that asks; every worker reads the
    same folder. Its `models/` and `hashes/` are read-only: a test that would change them fails (copy
    the entry first, as tests/test_faults.py does); the folder itself stays writable for other files."""
    from fakes import run_wide

    return run_wide(tmp_path_factory, "smollm2-cache", _dequantise_smollm2, read_only=("models", "hashes"))


@pytest.fixture
def smollm2_cache_env(smollm2_cache, monkeypatch):
    """ILLM_CACHE_DIR set to `smollm2_cache`, for tests that load the embedded model by name through
    a command or a backend rather than with `cache_dir=`."""
    monkeypatch.setenv("ILLM_CACHE_DIR", str(smollm2_cache))
    return smollm2_cache


def plain_scores(lm, context: str, candidates: list[str]) -> list[list[float]]:
    """Reference: one full forward per candidate over ids(context + candidate), log_softmax,
    gather; the candidate's tokens are those after the common prefix with ids(context)."""
    import torch

    context_ids = lm.encode(context)
    out = []
    for cand in candidates:
        ids = lm.encode(context + cand)
        start = next((i for i, (a, b) in enumerate(zip(ids, context_ids)) if a != b),
                     min(len(ids), len(context_ids)))
        with torch.inference_mode():
            logits = lm.model(input_ids=torch.tensor([ids])).logits[0].float()
        logprobs = torch.log_softmax(logits, dim=-1)
        out.append([float(logprobs[t - 1, ids[t]]) for t in range(start, len(ids))])
    return out


@pytest.fixture(scope="module")
def one_torch_thread():
    """For modules of tiny nets: one thread is as fast, and immune to a busy second core."""
    from illm_tools.rl.threads import torch_threads

    with torch_threads(1):
        yield


@pytest.fixture
def model_cache_in_tmp(tmp_path, monkeypatch):
    """Point illm's model cache (ILLM_CACHE_DIR) at the test's own folder; modules that load
    local tiny models use it with `pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")`."""
    monkeypatch.setenv("ILLM_CACHE_DIR", str(tmp_path / "illm-cache"))


def collect_babyai(tmp_path_factory, steps: int, seed: int, action_space: str):
    """A small random-policy BabyAI GoToLocal trajectory dataset in a fresh folder."""
    from illm_tools.collect import CollectConfig, collect

    out = tmp_path_factory.mktemp("traj") / "gotolocal"
    collect(CollectConfig(env_id="BabyAI-GoToLocal-v0", out=out, steps=steps, num_envs=4, seed=seed,
                          action_space=action_space))
    return out


def _skip_gpu_tests(items) -> None:
    """`gpu`-marked tests run where torch sees a CUDA GPU and are skipped, saying so, elsewhere."""
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (torch.cuda.is_available() is False)")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """The `gpu` tests' skips (`_skip_gpu_tests`), and `_keep_xdist_groups`."""
    _skip_gpu_tests(items)
    _keep_xdist_groups(items)


def _keep_xdist_groups(items) -> None:
    """Keep `--dist loadgroup`'s groups (`make test`): pytest-xdist names a test's group by a suffix it
    writes to `item._nodeid` (its worker's own collection hook), which pytest 9 no longer reads (the
    nodeid is `item._id`), so every group's tests were spread over the workers, and
    tests/test_vllm_engine.py's servers started in both of them (two pairs of vLLM servers on two
    cores, and a port one worker's server took given to the other's). Runs after xdist's hook and
    moves the name it wrote to where pytest reads it (the hook runs last)."""
    from _pytest.nodeid import coerce_node_id

    for item in items:
        named = getattr(item, "_nodeid", None)
        if isinstance(named, str) and named != item.nodeid:
            item._id = coerce_node_id(named)


_FREE_GB_NEEDED = 2.0
"""What a run needs free where its temporary folders go: the whole suite's folders under
/tmp/pytest-of-<user> peaked at 1.1 GB (a fresh-clone `make test` sampled every 4 s; each passing
test's folder is removed at its teardown, pyproject.toml's tmp_path_retention_policy)."""


def pytest_sessionstart(session):
    """Stop at once, with one line, where the disk cannot hold the run's temporary folders: a run that
    fills the disk fails tests at random, minutes in, with `No space left on device` in their set-up."""
    import shutil
    import tempfile
    from pathlib import Path

    if os.environ.get("PYTEST_XDIST_WORKER"):
        return  # the controller checked
    root = Path(session.config.option.basetemp or tempfile.gettempdir()).absolute()
    where = next(folder for folder in (root, *root.parents) if folder.is_dir())  # `--basetemp` may not exist yet
    free = shutil.disk_usage(where).free / 1e9
    if free < _FREE_GB_NEEDED:
        pytest.exit(f"only {free:.1f} GB free in {root}; the tests need about {_FREE_GB_NEEDED:.0f} GB for their "
                    f"temporary folders: free some (old /tmp/pytest-of-* folders?) and run again", returncode=1)
