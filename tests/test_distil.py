"""`illm distil`: a tiny random model distilled on a small oracle cache learns the teacher's ranking
(the loss falls, it ranks the teacher's best action first more often than its base), through the
annotator's own scoring path; an interrupted run resumes to the very student an uninterrupted one
makes; the student is a model folder `--model PATH` loads, with its own fingerprint; bad inputs get
one line and leave nothing behind. Also `illm collect --policy bot`, the student's lessons' source.

One module past 400 lines: its fixtures (an oracle cache, a tiny model, a student distilled once) are
built once per module and every test reads them; split, each part would build them again."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cli.main import app
from illm_tools.tasks.prompt_config import PromptConfig

runner = CliRunner()
pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module", autouse=True)
def model_cache(tmp_path_factory):
    """illm's model cache (file hashes) in a folder of this module's own."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("ILLM_CACHE_DIR", str(tmp_path_factory.mktemp("illm-cache")))
        yield
SMALL = dict(held_out=24, states=64, max_tokens=1024, batch_size=8, rank=8, save_every=4, learning_rate=3e-3)
"""A distillation the tiny model finishes in seconds (its byte-level tokenizer makes long prompts)."""


@pytest.fixture(scope="module")
def oracle_cache(tmp_path_factory):
    """BabyAI UnlockLocal states of the bot's episodes, annotated by the oracle (history 0)."""
    from illm_tools.annotate.bulk import AnnotateConfig, annotate_dataset
    from illm_tools.collect import CollectConfig, collect
    from illm_tools.llm.spec import LLMSpec

    tmp = tmp_path_factory.mktemp("distil-data")
    collect(CollectConfig(env_id="BabyAI-UnlockLocal-v0", out=tmp / "traj", steps=400, num_envs=4, seed=1000,
                          policy="bot"))
    annotate_dataset(AnnotateConfig(data=tmp / "traj", cache=tmp / "ann", llm=LLMSpec(backend="oracle"), setup=PromptConfig(history_len=0)))
    return tmp / "ann"


@pytest.fixture(scope="module")
def tiny_folder(tiny_lm):
    return tiny_lm.spec.path


def _distil(cache, out, student, **options):
    from illm_tools.distil.config import DistilConfig
    from illm_tools.distil.run import distil

    return distil(DistilConfig(cache=cache, out=out, student=student, **{**SMALL, **options}))


@pytest.fixture(scope="module")
def distilled(oracle_cache, tiny_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("students") / "tiny-student"
    return _distil(oracle_cache, out, tiny_folder, epochs=3), out


def test_the_student_learns_the_teachers_ranking(distilled):
    result, out = distilled
    assert not result.stopped and result.steps == result.steps_done == 24  # 3 epochs of 64 states, 8 a step
    assert result.left_out_long == 0 and result.train_states == 64
    assert result.loss_last < 0.6 * result.loss_first
    base, student = result.base_measure, result.student_measure
    assert student["states"] == base["states"] > 0
    assert student["agreement"] > base["agreement"] + 0.2  # the teacher's best action first, held-out states
    assert student["ranking_kl"] < 0.5 * base["ranking_kl"]
    assert student["text_nll"] < base["text_nll"]
    report = json.loads((out / "distil" / "report.json").read_text())
    assert report["student_measure"] == student


def test_the_student_is_a_model_folder_with_its_own_fingerprint(distilled, tiny_folder):
    """`--model PATH` loads it offline as any model folder; its fingerprint (a digest of its files)
    differs from its base's, so its cache rows never mix with the base's."""
    from illm_tools.llm.spec import LLMSpec

    result, out = distilled
    student, base = LLMSpec(model=str(out), dtype="float32"), LLMSpec(model=str(tiny_folder), dtype="float32")
    assert student.fingerprint() == result.student_fingerprint != base.fingerprint() == result.base_fingerprint
    assert (out / "config.json").is_file() and (out / "model.safetensors").is_file()
    assert not any(p.name.startswith(".tmp") for p in out.iterdir())
    info = json.loads((out / "illm_student.json").read_text())
    assert info["teacher"] == "oracle" and info["base_fingerprint"] == result.base_fingerprint
    loaded = student.load()
    assert not any(n.startswith("base_model") or "lora" in n for n, _ in loaded.lm.model.named_parameters())


def test_the_students_scores_are_the_annotators(distilled, oracle_cache):
    """The held-out agreement measured through the training forward is the agreement of the saved
    student scored by the annotator's own path (`Backend.score`, the rows `illm annotate` writes)."""
    import numpy as np

    from illm_tools.cache.store import AnnotationCache
    from illm_tools.distil.lessons import LessonPlan, lessons_from_plan
    from illm_tools.llm.spec import LLMSpec

    result, out = distilled
    plan = LessonPlan.from_json((out / "distil" / "lessons.json").read_text())
    lessons = lessons_from_plan(AnnotationCache(oracle_cache), plan.held_out)
    backend = LLMSpec(model=str(out), dtype="float32").load()
    actions = [t for lesson in lessons for t in lesson.targets if t.kind == "ranking"]
    scores = backend.score([t.prompt for t in actions], [list(t.candidates) for t in actions])
    agree = np.mean([s.best == t.best for s, t in zip(scores, actions)])
    assert agree == pytest.approx(result.student_measure["agreement"])


def test_the_training_forward_is_the_annotators_scoring(tiny_folder, oracle_cache, tmp_path):
    """The training forward (autograd on, the shared prompt prefix once, batched) scores the
    candidates as `score_candidates` does, and a text's log-likelihood as a plain forward does."""
    import math

    import torch

    from illm_tools.cache.store import AnnotationCache
    from illm_tools.distil.lessons import COLUMNS, lessons_of, text_target, tokenise
    from illm_tools.distil.loss import example_work
    from illm_tools.llm.loading import load_model
    from illm_tools.llm.driver import branch_sums, run_batch, score_candidates
    from conftest import plain_scores

    tiny_lm = load_model(str(tiny_folder), dtype="float32", cache_dir=tmp_path)
    tiny_lm.model.requires_grad_(True)
    rows = AnnotationCache(oracle_cache).table(COLUMNS).to_pylist()
    lessons = lessons_of(rows, ("action", "summary"))[:5]
    examples = [tokenise(tiny_lm, lesson) for lesson in lessons]
    assert all(e.shared for e in examples)
    works = [example_work(e) for e in examples]
    run = run_batch(tiny_lm, works, grad=True)  # the training forward
    for task, n in (("action", 0), ("summary", 1)):
        rows, values = run.scored[task]
        assert rows == list(range(len(examples)))
        sums = branch_sums(values, [w.branches[task] for w in works])
        assert all(s.requires_grad for s in sums)
        targets = [lesson.targets[n] for lesson in lessons]
        if task == "action":
            want = score_candidates(tiny_lm, [t.prompt for t in targets], [list(t.candidates) for t in targets])
            for s, w in zip(sums, want):
                assert s.detach().tolist() == pytest.approx(w.sums, abs=1e-4)
        else:
            for s, t in zip(sums, targets):
                eos = tiny_lm.tokenizer.convert_ids_to_tokens(tiny_lm.eos_ids[0])
                plain = plain_scores(tiny_lm, t.prompt, [text_target(t.text) + eos])
                assert float(s[0]) == pytest.approx(math.fsum(plain[0]), abs=1e-3)
    torch.stack([s.sum() for s in sums]).sum().backward()  # the graph reaches the weights
    assert float(tiny_lm.model.model.layers[0].mlp.up_proj.weight.grad.abs().sum()) > 0


def test_the_argmax_target_is_the_cross_entropy_of_the_teachers_top_action(tiny_folder, oracle_cache, tmp_path):
    """--ranking-target argmax: the ranking loss is -log p_student(teacher's top candidate), the
    texts' loss unchanged, and the KL reported beside it the same as under the distribution target."""
    import torch

    from illm_tools.cache.store import AnnotationCache
    from illm_tools.distil.lessons import COLUMNS, lessons_of, tokenise
    from illm_tools.distil.loss import lesson_loss
    from illm_tools.distil.config import DistilConfig
    from illm_tools.llm.loading import load_model
    from illm_tools.llm.driver import branch_sums
    from illm_tools.llm.scoring import StatePlan, continuation_logprobs, extend

    lm = load_model(str(tiny_folder), dtype="float32", cache_dir=tmp_path)
    rows = AnnotationCache(oracle_cache).table(COLUMNS).to_pylist()
    examples = [tokenise(lm, lesson) for lesson in lessons_of(rows, ("action", "summary"))[:6]]
    soft = lesson_loss(lm, examples, text_weight=0.5)
    hard = lesson_loss(lm, examples, text_weight=0.5, ranking_target="argmax")
    assert hard.ranking_kl == pytest.approx(soft.ranking_kl) and hard.text_nll == pytest.approx(soft.text_nll)
    shared = extend(lm, [list(e.shared) for e in examples])
    branches = [e.branches[0] for e in examples]
    plans = [StatePlan(list(b.suffix), [list(c) for c in b.continuations], list(b.skip)) for b in branches]
    state = extend(lm, [list(b.suffix) for b in branches], past=shared)  # the suffix run apart: a reference
    sums = branch_sums(continuation_logprobs(lm, state, [p.continuations for p in plans]), plans)
    cross_entropy = torch.stack([-torch.log_softmax(s, 0)[b.best] for s, b in zip(sums, branches)]).mean()
    assert float(hard.loss) == pytest.approx(float(cross_entropy) + 0.5 * hard.text_nll, rel=1e-4)
    assert float(soft.loss) == pytest.approx(soft.ranking_kl + 0.5 * soft.text_nll, rel=1e-4)
    config = DistilConfig(cache=oracle_cache, out=tmp_path / "s", student=tiny_folder, ranking_target="argmax")
    assert config.settings()["ranking_target"] == "argmax"
    assert "ranking_target" not in DistilConfig(cache=oracle_cache, out=tmp_path / "s", student=tiny_folder).settings()


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_an_interrupted_distillation_resumes_to_the_same_student(oracle_cache, tiny_folder, tmp_path):
    from safetensors.torch import load_file

    from illm_tools.distil.config import DistilConfig
    from illm_tools.distil.run import distil

    calls = []

    def stop_after_5():
        calls.append(1)
        return len(calls) >= 5

    config = DistilConfig(cache=oracle_cache, out=tmp_path / "a", student=tiny_folder, **SMALL)
    first = distil(config, should_stop=stop_after_5)
    assert first.stopped and first.steps_done == 5 and not (tmp_path / "a" / "config.json").exists()
    assert sorted(p.name for p in (tmp_path / "a" / "distil" / "checkpoints").iterdir()) == \
        ["checkpoint-4", "checkpoint-5"]
    resumed = distil(config)
    assert resumed.resumed_from == 5 and resumed.steps_done == resumed.steps == 8 and not resumed.stopped
    whole = _distil(oracle_cache, tmp_path / "b", tiny_folder)
    a, b = load_file(tmp_path / "a" / "model.safetensors"), load_file(tmp_path / "b" / "model.safetensors")
    assert a.keys() == b.keys() and all(bool((a[k] == b[k]).all()) for k in a)
    assert [h["loss"] for h in resumed.log_history] == [h["loss"] for h in whole.log_history]
    # the training time and tokens are the whole training's: the first session's, up to its checkpoint, and the
    # second's; the tokens those of the uninterrupted run
    spent = json.loads((tmp_path / "a" / "distil" / "checkpoints" / "checkpoint-5" / "illm_checkpoint.json").read_text())
    assert 0 < spent["spent"]["seconds"] <= first.train_seconds < resumed.train_seconds
    assert round(resumed.train_tokens_per_s * resumed.train_seconds) == round(whole.train_tokens_per_s *
                                                                              whole.train_seconds)
    again = distil(config)  # the student is there: nothing is trained again
    assert again.already and again.student_measure == resumed.student_measure


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_a_damaged_checkpoint_is_set_aside_and_an_older_one_resumes(oracle_cache, tiny_folder, tmp_path):
    from illm_tools.distil.config import DistilConfig
    from illm_tools.distil.run import distil

    calls = []
    config = DistilConfig(cache=oracle_cache, out=tmp_path / "s", student=tiny_folder, **{**SMALL, "save_every": 2})
    assert distil(config, should_stop=lambda: calls.append(1) or len(calls) >= 5).stopped
    checkpoints = tmp_path / "s" / "distil" / "checkpoints"
    newest = checkpoints / "checkpoint-5" / "optimizer.pt"
    newest.write_bytes(newest.read_bytes()[:100])  # cut short, as a kill while writing leaves it
    resumed = distil(config)
    assert resumed.resumed_from == 4 and not resumed.stopped
    assert [p.name.split("-")[:2] for p in (tmp_path / "s" / "distil" / "damaged").iterdir()] == [["checkpoint", "5"]]


def test_the_command_reports_in_illms_own_lines(oracle_cache, tiny_folder, tmp_path):
    out = tmp_path / "student"
    args = ["distil", str(oracle_cache), "--student", str(tiny_folder), "--out", str(out), "--held-out", "24",
            "--states", "32", "--max-tokens", "1024", "--rank", "4"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    text = result.output
    assert f"distilled oracle's action,summary into {out}" in text and "32 training states, 24 held out" in text
    assert "agreement with the teacher's top action" in text and f"--model {out}" in text
    for noise in ("Writing model shards", "it/s]", "Warning", "WARNING", "deprecated", "{'loss'"):
        assert noise not in text
    again = runner.invoke(app, args)
    assert again.exit_code == 0 and "already holds this student" in again.output


@pytest.mark.parametrize("rank", [4, 0])
def test_layers_trains_the_top_blocks_only(oracle_cache, tiny_folder, tmp_path, rank):
    """--layers N: adapters (or, at rank 0, trained weights) in the top N blocks only, so the saved
    student's weights differ from its base's in those blocks and nowhere else."""
    from safetensors.torch import load_file

    out = tmp_path / f"top-rank{rank}"
    result = _distil(oracle_cache, out, tiny_folder, states=16, rank=rank, layers=1)
    assert not result.stopped and (out / "config.json").is_file()
    folder = Path(tiny_folder)
    base, student = load_file(next(iter(folder.glob("*.safetensors")))), load_file(out / "model.safetensors")
    blocks = json.loads((folder / "config.json").read_text())["num_hidden_layers"]
    top = f"layers.{blocks - 1}."
    changed = {name for name in base if not (base[name] == student[name]).all()}
    assert changed and all(top in name for name in changed), changed
    assert json.loads((out / "distil" / "settings.json").read_text())["layers"] == 1


def test_blocks_keeps_evenly_spaced_blocks_and_saves_a_model_of_that_many(oracle_cache, tmp_path):
    """--blocks N: N of the student's blocks, first and last among them; the cut model is an ordinary
    N-block model of its class (its logits those of a fresh N-block model given the kept blocks'
    weights; the annotator's KV-cached scoring works on it), and the saved student has N blocks."""
    import torch
    from safetensors.torch import load_file
    from transformers import AutoConfig, AutoModelForCausalLM

    from conftest import _tiny_model, _train_tokenizer, plain_scores
    from illm_tools.distil.training import keep_blocks, kept_indices
    from illm_tools.llm.loading import load_model
    from illm_tools.llm.driver import score_candidates

    assert kept_indices(30, 10) == [0, 3, 6, 10, 13, 16, 19, 23, 26, 29] and kept_indices(4, 1) == [0]
    assert kept_indices(4, 4) == [0, 1, 2, 3]
    folder = tmp_path / "four-blocks"
    _tiny_model(folder, len(_train_tokenizer(folder, add_bos=False)), "llama", layers=4)
    lm = load_model(str(folder), dtype="float32", cache_dir=tmp_path / "cache")
    base = load_file(folder / "model.safetensors")
    assert keep_blocks(lm.model, 2) == [0, 3] and lm.model.config.num_hidden_layers == 2
    assert [block.self_attn.layer_idx for block in lm.model.model.layers] == [0, 1]
    config = AutoConfig.from_pretrained(folder)
    config.num_hidden_layers = 2
    fresh = AutoModelForCausalLM.from_config(config)
    renamed = {k.replace("layers.3.", "layers.1."): v for k, v in base.items() if "layers.1." not in k
               and "layers.2." not in k}
    missing, unexpected = fresh.load_state_dict(renamed, strict=False)
    assert not unexpected and set(missing) <= {"lm_head.weight"}  # tied to the embeddings
    fresh.tie_weights()
    ids = torch.tensor([lm.encode("You see a red key 1 step forward. go forward")])
    with torch.inference_mode():
        assert torch.allclose(lm.model(input_ids=ids).logits, fresh(input_ids=ids).logits, atol=1e-5)
    context, candidates = "The goal is: open the door. Answer: ", ["turn left", "go forward", "toggle"]
    got = score_candidates(lm, [context], [candidates])[0]
    want = [sum(t) for t in plain_scores(lm, context, candidates)]
    assert got.sums == pytest.approx(want, abs=1e-4)

    out = tmp_path / "two-block-student"
    result = _distil(oracle_cache, out, str(folder), states=16, blocks=2)
    assert not result.stopped and json.loads((out / "config.json").read_text())["num_hidden_layers"] == 2
    assert not any("layers.2." in k for k in load_file(out / "model.safetensors"))
    assert json.loads((out / "distil" / "settings.json").read_text())["blocks"] == 2
    assert load_model(str(out), dtype="float32", cache_dir=tmp_path / "cache").model.config.num_hidden_layers == 2


def test_blocks_keeps_the_kinds_of_attention_of_the_kept_blocks(tiny_lm_sliding, tmp_path):
    """Gemma 3's per-block attention kinds (sliding or full) follow the blocks kept."""
    from illm_tools.distil.training import keep_blocks
    from illm_tools.llm.loading import load_model

    lm = load_model(str(tiny_lm_sliding.spec.path), dtype="float32", cache_dir=tmp_path)
    assert keep_blocks(lm.model, 1) == [0]
    assert lm.model.config.get_text_config().layer_types == ["sliding_attention"]


def test_balanced_quotas_share_the_lessons_between_actions():
    from illm_tools.distil.lessons import balanced_quotas

    counts = {"go forward": 8000, "turn right": 3000, "turn left": 2800, "pick up": 120, "toggle": 36}
    assert balanced_quotas(counts, 1700, 0.0) == {"go forward": 975, "turn right": 365, "turn left": 341,
                                                  "pick up": 15, "toggle": 4}  # the cache's own shares
    half = balanced_quotas(counts, 1700, 0.5)  # shares as the square roots of the counts
    assert sum(half.values()) == 1700 and half["pick up"] == 87 and half["go forward"] == 710
    assert set(balanced_quotas(counts, 1700, 1.0).values()) == {340}  # equal: toggle's 36 states 9-10 times each
    assert balanced_quotas({"a": 5, "b": 0}, 3, 1.0) == {"a": 3, "b": 0}


def test_min_share_raises_the_rare_actions_and_keeps_the_common_ones_proportions(oracle_cache, tiny_folder, tmp_path):
    """--min-share: every top action at least that share of the lessons (or of the --visits draws), the
    others keeping their proportions to one another, where --balance's power moves them together."""
    import collections

    from illm_tools.cache.store import AnnotationCache
    from illm_tools.distil.lessons import balanced_quotas, floor_shares, lessons_from_plan, top_action, visit_balance
    from illm_tools.distil.config import DistilConfig
    from illm_tools.distil.run import _new_plan

    shares = {"go forward": 0.57, "turn right": 0.21, "turn left": 0.19, "pick up": 0.025, "toggle": 0.005}
    floored = floor_shares(shares, 0.08)
    assert floored["pick up"] == floored["toggle"] == 0.08 and abs(sum(floored.values()) - 1) < 1e-12
    assert abs(floored["go forward"] / floored["turn left"] - 0.57 / 0.19) < 1e-9  # the common ones' ratio kept
    assert floor_shares(shares, 0.0) == shares and floor_shares({"a": 0.9, "b": 0.1, "c": 0.0}, 0.5) == \
        {"a": 0.5, "b": 0.5, "c": 0.0}
    assert floor_shares({"a": 0.7, "b": 0.2, "c": 0.1}, 0.25) == {"a": 0.5, "b": 0.25, "c": 0.25}  # b pushed below too
    counts = {"go forward": 8000, "turn right": 3000, "turn left": 2800, "pick up": 120, "toggle": 36}
    quotas = balanced_quotas(counts, 1700, 0.0, min_share=0.08)
    assert sum(quotas.values()) == 1700 and quotas["pick up"] == quotas["toggle"] == 136
    assert abs(quotas["go forward"] / quotas["turn left"] - 8000 / 2800) < 0.01
    powered = balanced_quotas(counts, 1700, 0.75)  # the power evens go forward and turn left as well
    assert powered["go forward"] / powered["turn left"] < 1.4 < quotas["go forward"] / quotas["turn left"]
    factors = visit_balance(["a", "b", "a"], [1.0, 2.0, 7.0], 0.0, 0.3)  # a: 8 of 10 visits, b: 2
    draws = {"a": factors[0] * 1.0 + factors[2] * 7.0, "b": factors[1] * 2.0}
    assert abs(draws["b"] / (draws["a"] + draws["b"]) - 0.3) < 1e-9 and factors[0] == factors[2]

    cache = AnnotationCache(oracle_cache)
    traj = oracle_cache.parent / "traj"
    for visits in ([], [traj]):
        config = DistilConfig(cache=oracle_cache, out=tmp_path / f"m{len(visits)}", student=tiny_folder, visits=visits,
                              **{**SMALL, "states": 3000, "min_share": 0.1})
        plan = _new_plan(cache, config)
        top = collections.Counter(map(top_action, lessons_from_plan(cache, plan.train)))
        assert len(top) > 2 and min(top.values()) / 3000 > (0.099 if not visits else 0.08), top
        assert config.settings()["min_share"] == 0.1


def test_balance_teaches_the_rare_actions_more_often(oracle_cache, tiny_folder, tmp_path):
    """--balance: the lessons' top actions nearer equal shares, a rare action's states repeated; the
    held-out states unchanged."""
    import collections

    from illm_tools.cache.store import AnnotationCache
    from illm_tools.distil.lessons import LessonPlan, lessons_from_plan, top_action
    from illm_tools.distil.config import DistilConfig
    from illm_tools.distil.run import _new_plan

    cache = AnnotationCache(oracle_cache)

    def plan(balance):
        config = DistilConfig(cache=oracle_cache, out=tmp_path / f"b{balance}", student=tiny_folder,
                              **{**SMALL, "states": 200, "balance": balance})
        return _new_plan(cache, config)

    natural, even = plan(0.0), plan(1.0)
    assert natural.held_out == even.held_out and len(natural.train) == len(even.train) == 200
    shares = [collections.Counter(map(top_action, lessons_from_plan(cache, p.train))) for p in (natural, even)]
    assert max(shares[1].values()) - min(shares[1].values()) <= 1 < max(shares[0].values()) - min(shares[0].values())
    repeated = [k for k, n in collections.Counter(even.train).items() if n > 1]
    assert repeated and not set(even.train) & set(even.held_out)
    assert all(a != b for a, b in zip(even.train, even.train[1:]))  # a state's repeats are spread out
    assert LessonPlan.from_json(even.to_json()) == even


def test_visits_draw_the_lessons_as_often_as_an_agent_meets_their_states(oracle_cache, tiny_folder, tmp_path):
    """--visits: every lesson's state is found in the trajectories the cache was annotated from, and
    the lessons are drawn in proportion to the steps spent in each state (seeded, repeatable)."""
    import collections

    from illm_tools.cache.store import AnnotationCache
    from illm_tools.distil.lessons import COLUMNS, lessons_of, visits_of
    from illm_tools.distil.config import DistilConfig
    from illm_tools.distil.run import _new_plan

    traj = oracle_cache.parent / "traj"
    cache = AnnotationCache(oracle_cache)
    lessons = lessons_of(cache.table(COLUMNS).to_pylist(), ("action", "summary"))
    visits = visits_of([traj], [0])
    assert sum(visits.values()) == 400 and all(visits[lesson.state] > 0 for lesson in lessons)

    def plan(seed):
        config = DistilConfig(cache=oracle_cache, out=tmp_path / "v", student=tiny_folder, visits=[traj],
                              **{**SMALL, "states": 2000, "seed": seed})
        return _new_plan(cache, config)

    drawn = plan(0)
    assert drawn == plan(0) != plan(1) and len(drawn.train) == 2000 and not set(drawn.train) & set(drawn.held_out)
    by_state = {tuple(t.key for t in lesson.targets): visits[lesson.state] for lesson in lessons}
    taught = {k: v for k, v in by_state.items() if k not in set(drawn.held_out)}
    most = max(taught, key=taught.get)
    counts = collections.Counter(drawn.train)
    expected = 2000 * taught[most] / sum(taught.values())
    assert abs(counts[most] - expected) < 4 * expected ** 0.5  # the most visited state: as often as it is met


def test_balance_on_visits_evens_the_actions_shares_of_the_draws(oracle_cache, tiny_folder, tmp_path):
    """--visits with --balance: each top action's share of the draws goes from its share of the visits
    toward equal (its visits' share to the power 1 - balance), the states never visited still untaught."""
    import collections

    from illm_tools.cache.store import AnnotationCache
    from illm_tools.distil.lessons import lessons_from_plan, top_action, visit_balance, visits_of
    from illm_tools.distil.config import DistilConfig
    from illm_tools.distil.run import _new_plan

    assert list(visit_balance(["a", "b", "a"], [1.0, 4.0, 3.0], 0.5)) == [0.5, 0.5, 0.5]  # a: 4 visits, b: 4
    assert list(visit_balance(["a", "b"], [1.0, 4.0], 1.0)) == [1.0, 0.25]
    traj = oracle_cache.parent / "traj"
    cache = AnnotationCache(oracle_cache)
    visits = visits_of([traj], [0])

    def shares(balance):
        config = DistilConfig(cache=oracle_cache, out=tmp_path / f"vb{balance}", student=tiny_folder, visits=[traj],
                              **{**SMALL, "states": 4000, "balance": balance})
        plan = _new_plan(cache, config)
        assert all(visits[lesson.state] > 0 for lesson in lessons_from_plan(cache, plan.train[:50]))
        counts = collections.Counter(map(top_action, lessons_from_plan(cache, plan.train)))
        return {a: n / 4000 for a, n in counts.items()}

    natural, half, even = shares(0.0), shares(0.5), shares(1.0)
    assert len(natural) > 1 and natural.keys() == half.keys() == even.keys()
    rarest = min(natural, key=natural.get)
    assert natural[rarest] < half[rarest] < even[rarest]
    assert max(even.values()) - min(even.values()) < 0.05


# --- bad inputs: one line, a non-zero exit, nothing written -------------------------------------------
def _refused(args, out, *expected):
    result = runner.invoke(app, ["distil", *args, "--out", str(out)])
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    assert "Traceback" not in result.output
    for part in expected:
        assert part in lines[0], lines[0]
    return lines[0]


def test_bad_inputs_get_one_line(oracle_cache, tiny_folder, tmp_path):
    from illm_tools.annotate.bulk import AnnotateConfig, annotate_dataset
    from illm_tools.cache import layout
    from illm_tools.collect import CollectConfig, collect
    from illm_tools.llm.spec import LLMSpec

    out = tmp_path / "student"
    student = ["--student", str(tiny_folder)]
    _refused([str(tmp_path / "nowhere"), *student], out, "no annotation cache at", "illm annotate")
    empty = tmp_path / "empty"
    empty.mkdir()
    _refused([str(empty), *student], out, "is empty", "illm annotate")
    layout.write_manifest(empty, layout.empty_manifest())  # a cache whose manifest lists no shard
    _refused([str(empty), *student], out, "is empty", "illm annotate")
    _refused([str(tmp_path), *student], out, "is not an annotation cache")
    collect(CollectConfig(env_id="BabyAI-GoToLocal-v0", out=tmp_path / "traj", steps=40, num_envs=2))
    annotate_dataset(AnnotateConfig(data=tmp_path / "traj", cache=tmp_path / "summaries", llm=LLMSpec(backend="oracle"),
                                    setup=PromptConfig(history_len=0), tasks=("summary",)))
    _refused([str(tmp_path / "summaries"), *student], out, "holds no action rows", "--tasks action,summary")
    _refused([str(oracle_cache), "--student", str(tmp_path / "no-model")], out, "no-model")
    (tmp_path / "not-a-model").mkdir()
    _refused([str(oracle_cache), "--student", str(tmp_path / "not-a-model")], out, "no config.json")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "config.json").write_text("{not json")
    _refused([str(oracle_cache), "--student", str(broken)], out, "cannot be loaded")
    _refused([str(oracle_cache), *student, "--teacher", "llama3"], out, "no rows of the teacher 'llama3'", "oracle")
    _refused([str(oracle_cache), *student, "--held-out", "100000"], out, "--held-out")
    _refused([str(oracle_cache), *student, "--tasks", "summary"], out, "no ranking task")
    _refused([str(oracle_cache), *student, "--dtype", "float16"], out, "--dtype")
    _refused([str(oracle_cache), *student, "--layers", "99"], out, "--layers 99 is more than", "transformer blocks")
    _refused([str(oracle_cache), *student, "--layers", "0"], out, "--layers must be positive")
    _refused([str(oracle_cache), *student, "--blocks", "99"], out, "--blocks 99 is more than", "transformer blocks")
    _refused([str(oracle_cache), *student, "--balance", "2"], out, "--balance must be between 0 and 1")
    _refused([str(oracle_cache), *student, "--min-share", "0.9"], out, "--min-share 0.9 is more than 1 /")
    _refused([str(oracle_cache), *student, "--ranking-target", "top"], out, "--ranking-target must be")
    _refused([str(oracle_cache), *student, "--visits", str(tmp_path / "nowhere")], out, "nowhere")
    assert not out.exists()
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    _refused([str(oracle_cache), *student], out, "not a distillation's")
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_a_different_distillation_in_the_same_folder_is_refused(oracle_cache, tiny_folder, tmp_path):
    out = tmp_path / "s"
    assert _distil(oracle_cache, out, tiny_folder, states=16).train_states == 16
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    _refused([str(oracle_cache), "--student", str(tiny_folder), "--held-out", "24", "--states", "16",
              "--max-tokens", "1024", "--rank", "4"], out, "other settings", "rank=8")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before


# --- where the lessons come from: the BabyAI bot as a collection policy --------------------------------
def test_collect_with_the_bot_logs_the_experts_episodes(tmp_path):
    from illm_tools.collect import CollectConfig, collect

    summary = collect(CollectConfig(env_id="BabyAI-GoToLocal-v0", out=tmp_path / "t", steps=300, num_envs=4,
                                    policy="bot", bot_epsilon=0.0))
    assert summary["policy"] == "bot" and summary["episodes_finished"] >= 10 and summary["success_rate"] == 1.0
    result = runner.invoke(app, ["collect", "--env", "MiniGrid-DoorKey-5x5-v0", "--policy", "bot", "--steps", "10",
                                 "--out", str(tmp_path / "u")])
    assert result.exit_code == 1 and "BabyAI-*" in result.output and not (tmp_path / "u").exists()


@pytest.mark.slow
def test_the_embedded_model_distils_into_a_student_probe_and_annotate_load(oracle_cache, tmp_path,
                                                                           smollm2_cache_env):
    """SmolLM2-135M (the GGUF de-quantised, tied embeddings) through the whole command: a few steps,
    the merged student saved, then `illm probe` and `illm annotate` read it with `--model PATH`."""
    out = tmp_path / "smollm2-student"
    result = runner.invoke(app, ["distil", str(oracle_cache), "--student", "smollm2-135m", "--out", str(out),
                                 "--held-out", "8", "--states", "16", "--rank", "4"])
    assert result.exit_code == 0, result.output
    assert "16 training states, 8 held out; 2 steps" in result.output
    probe = runner.invoke(app, ["probe", "--env", "BabyAI-UnlockLocal-v0", "--model", str(out), "--dtype", "float32",
                                "--states", "6"])
    assert probe.exit_code == 0 and probe.output.startswith(f"probe {out} (float32)"), probe.output
    traj = tmp_path / "traj"
    assert runner.invoke(app, ["collect", "--env", "BabyAI-UnlockLocal-v0", "--policy", "bot", "--steps", "8",
                               "--num-envs", "2", "--seed", "5", "--out", str(traj)]).exit_code == 0
    annotated = runner.invoke(app, ["annotate", str(traj), "--cache", str(tmp_path / "ann"), "--model", str(out),
                                    "--dtype", "float32", "--history", "0"])
    assert annotated.exit_code == 0 and "annotated" in annotated.output, annotated.output
