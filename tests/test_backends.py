"""The LLM backend seam: an unknown backend is refused in one line, the stub answers
deterministically from the prompt, a backend defined in this test file plugs in through the
registry (one class plus one entry) and annotates and trains unchanged (the whole pipeline on the
stub, text and hop mode alike: tests/test_pipeline.py)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.annotate.engine import Annotator
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.llm.backend import BACKENDS, Backend, backend_fingerprint, backend_hidden_size, load_backend
from illm_tools.llm.stub import StubBackend
from illm_tools.tasks.state import StateRecord
from fakes import TinyBackend, cli_ok as ok

runner = CliRunner()
ACTIONS = ("turn left", "turn right", "go forward")


def test_an_unknown_backend_is_refused_in_one_line(tmp_path):
    with pytest.raises(UsageError, match="unknown LLM backend 'vllm'; choose one of transformers, stub"):
        load_backend("vllm", "smollm2-135m")
    out = runner.invoke(app, ["annotate", str(tmp_path), "--backend", "vllm"])
    assert out.exit_code == 1 and "unknown LLM backend" in out.output and "Traceback" not in out.output


def test_the_stub_answers_deterministically_from_the_prompt():
    a, b = StubBackend("stub:32"), StubBackend("stub:32")
    assert isinstance(a, Backend) and a.hidden_size == 32 and backend_hidden_size("stub", "stub:32") == 32
    assert a.fingerprint == backend_fingerprint("stub", "stub:32") != StubBackend("other:32").fingerprint
    s1, s2 = a.score(["ctx"], [[" go", " stop"]])[0], b.score(["ctx"], [[" go", " stop"]])[0]
    assert s1.sums == s2.sums and s1.sums[0] != s1.sums[1]
    assert a.score(["other ctx"], [[" go"]])[0].sums != s1.sums[:1]
    g1, g2 = a.generate(["p"])[0], b.generate(["p"])[0]
    assert g1.text == g2.text and np.array_equal(g1.embedding, g2.embedding) and g1.embedding.shape == (32,)
    assert a.input_embeddings().shape[1] == 32 and a.last_hidden([a.input_embeddings()[:3]]).shape == (1, 32)



def test_a_backend_registered_from_a_test_file_annotates_and_trains(tmp_path):
    BACKENDS["tiny"] = TinyBackend
    try:
        lm = load_backend("tiny", "m:16")
        assert lm.fingerprint["model_id"] == "tiny:m:16" and lm.hidden_size == 16
        cache = AnnotationCache(tmp_path / "ann")
        records = [StateRecord("go to the ball", (), f"You see a ball {k} steps forward", ACTIONS) for k in range(4)]
        stats = Annotator(lm, cache, model="m:16", history_len=0).annotate_states(records, "BabyAI-GoToLocal-v0",
                                                                                 "babyai-text@1")
        assert stats.annotated_states == 4 and len(cache) == 8
        ok("collect", "--env", "BabyAI-GoToLocal-v0", "--steps", 64, "--num-envs", 2, "--out", tmp_path / "traj")
        ok("train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--cache", tmp_path / "ann", "--backend",
           "tiny", "--model", "m:16", "--history", 0, "--num-envs", 2, "--num-steps", 16, "--frames", 32,
           "--live-budget", 4, "--live-mode", "sync", "--out", tmp_path / "run")
        with open(tmp_path / "run" / "metrics.csv", newline="") as fh:
            assert float(next(csv.DictReader(fh))["live_annotations"]) == 4
    finally:
        BACKENDS.pop("tiny")




def test_a_plugged_backend_folds_its_own_options_into_its_spec_without_being_named(tmp_path):
    """The hooks a backend class may carry (`model_options`/`model_spec`, `selecting_options`, `quantises`,
    `setting_of`): the code around the registry asks the class, never the backend's name."""
    from illm_tools.llm.backend import backend_quant, resolve_model, selecting_options
    from illm_tools.rl.compare import comparable

    class Knobbed(TinyBackend):
        model_options = ("oracle_noise",)  # borrows the oracle's option: the owner named in refusals stays the oracle
        quantises = False

        @staticmethod
        def model_spec(model, *, oracle_noise=0.0):  # a spec already is its own spec
            return model if model and "~" in model else f"{model or 'm:16'}~{oracle_noise:g}"

        @staticmethod
        def selecting_options(model):
            return f"--backend knobbed --model {model.split('~')[0]} --oracle-noise {model.split('~')[1]}"

        @staticmethod
        def setting_of(model):
            return {"oracle_noise": float(model.split("~")[1])}

    BACKENDS["knobbed"] = Knobbed
    try:
        assert resolve_model("knobbed", None, oracle_noise=0.25) == "m:16~0.25"
        assert selecting_options("knobbed", "m:16~0.25", "float32", "none") == "--backend knobbed --model m:16 --oracle-noise 0.25"
        assert backend_quant("knobbed", "m:16~0.25", "auto", "cuda") == "none"
        assert backend_quant("transformers", "smollm2-135m", "auto", "cpu") == "none"
        with pytest.raises(UsageError, match="^--endpoint is the openai backend's: add --backend openai .this command "
                                             "uses --backend knobbed"):
            resolve_model("knobbed", None, endpoint="http://127.0.0.1:9/v1")
        ok("train", "--env", "BabyAI-GoToLocal-v0", "--method", "illm", "--backend", "knobbed", "--oracle-noise", 0.5,
           "--history", 0, "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", "all",
           "--live-mode", "sync", "--cache", tmp_path / "ann", "--out", tmp_path / "run")
        import json

        config = json.loads((tmp_path / "run" / "config.json").read_text())
        assert config["llm"]["model"] == "m:16~0.5"
        assert comparable(config)["oracle_noise"] == 0.5
    finally:
        BACKENDS.pop("knobbed")
