"""Targets for most training steps: frequency-first bulk annotation (`--limit` takes the most
visited states, a re-run annotates nothing, `--max-minutes` stops between chunks), `illm data
coverage`, the live fallback's priority (most visited over the run first), the async worker
(its rows land in the shared cache and reach a later rollout; killing it leaves the run going and
the cache valid), and the refusal of a cache that holds none of this run's setup."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import collect_babyai
from cli.main import app
from illm_tools.tasks.prompt_config import PromptConfig
from illm_tools.tasks.annotation_setup import AnnotationSetup, check_setup
from illm_tools.llm.spec import LLMSpec
from illm_tools.annotate.bulk import AnnotateConfig, annotate_dataset
from illm_tools.annotate.coverage import VisitedStates, ahead_warning, heldout_curve, measure_coverage
from illm_tools.annotate.engine import Annotator
from illm_tools.cache.store import AnnotationCache
from illm_tools.cache.verify import verify
from illm_tools.collect import CollectConfig, collect
from illm_tools.data.trajectories import open_table
from illm_tools.errors import CacheError
from illm_tools.rl.live import AsyncLive, SyncLive, WorkerSpec
from illm_tools.rl.targets import CachedTargets
from illm_tools.tasks.state import TABLE_COLUMNS, records_from_table
from fakes import cli_ok as ok, prompt_builder, serve_state as state

ENV = "BabyAI-GoToLocal-v0"
runner = CliRunner()


pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")


@pytest.fixture(scope="module")
def trajectories(tmp_path_factory):
    return collect_babyai(tmp_path_factory, steps=400, seed=3, action_space="original")


def config(trajectories, cache, tiny_lm, **kw) -> AnnotateConfig:
    return AnnotateConfig(data=trajectories, cache=cache, llm=LLMSpec(model=tiny_lm.spec.path, dtype="float32"), setup=PromptConfig(history_len=0),
                          batch_size=4, chunk=4, **kw)


def test_states_are_counted_most_visited_first():
    records = [state(1), state(2), state(2), state(3), state(3), state(3), state(4)]
    b = prompt_builder(model_fingerprint="x", model="m", history_len=0)
    visited = VisitedStates.count(records, [ENV] * 7, ["babyai-text@1"] * 7, lambda e, r: b, ("action", "summary"))
    assert visited.records == [state(3), state(2), state(1), state(4)]  # ties keep first visits first
    assert visited.steps.tolist() == [3, 2, 1, 1] and visited.total_steps == 7
    assert visited.top_k_curve((1, 2, 10)) == {1: 3 / 7, 2: 5 / 7, 10: 1.0}
    assert visited.keys[0] == b.state_keys(records[3])


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_limit_annotates_the_most_visited_states_and_a_rerun_annotates_nothing(trajectories, tmp_path, tiny_lm):
    cache = tmp_path / "ann"
    first = annotate_dataset(config(trajectories, cache, tiny_lm, limit=6))
    assert first.stats.annotated_states == 6 and first.covered_states == 6
    again = annotate_dataset(config(trajectories, cache, tiny_lm, limit=6))
    assert again.stats.annotated_states == 0 and again.stats.hits == again.stats.keys == 12
    # frequency order: these 6 states cover as many steps as any 6 states of the dataset can
    records, _ = records_from_table(open_table(trajectories, columns=TABLE_COLUMNS), 0)
    counts = sorted(np.unique([hash(r) for r in records], return_counts=True)[1], reverse=True)
    assert first.covered_step_share * first.dataset_steps == pytest.approx(sum(counts[:6]))
    assert first.selected_step_share == pytest.approx(first.covered_step_share)
    assert first.stats.summaries == 6 and 0 < first.stats.mean_summary_tokens <= 64
    more = annotate_dataset(config(trajectories, cache, tiny_lm, limit=8))
    assert more.stats.annotated_states == 2 and more.covered_step_share > first.covered_step_share


def test_max_minutes_stops_between_chunks_with_what_is_done_written(trajectories, tmp_path, tiny_lm, monkeypatch):
    from types import SimpleNamespace

    clock = iter(range(0, 10**6, 30))  # each reading of the engine's clock is 30 s later
    monkeypatch.setattr("illm_tools.annotate.engine.time",
                        SimpleNamespace(perf_counter=lambda: float(next(clock)), time=time.time))
    result = annotate_dataset(config(trajectories, tmp_path / "ann", tiny_lm, limit=20, max_minutes=1.5))
    assert result.stats.stopped_early and 0 < result.stats.annotated_states < 20
    assert result.stats.annotated_states % 4 == 0  # whole chunks only
    assert len(AnnotationCache(tmp_path / "ann")) == 2 * result.stats.annotated_states and verify(tmp_path / "ann").ok


def test_the_heldout_curve_counts_the_other_episodes_steps_only():
    # episodes (sorted) a, b, c, d: a and c are counted, b and d are held out
    steps = [("a", state(1)), ("a", state(1)), ("a", state(2)), ("b", state(1)), ("b", state(9)),
             ("c", state(3)), ("d", state(2)), ("d", state(8))]
    episodes, records = zip(*steps)
    curve = heldout_curve(records, [ENV] * 8, ["babyai-text@1"] * 8, episodes, ks=(1, 2))
    # the top 1 of a, c is state 1 (twice): 1 of the 4 held-out steps; top 2 adds state 2: 2 of 4
    assert curve == {"1": 0.25, "2": 0.5, "all": 0.5}
    other_env = heldout_curve(records, ["MiniGrid-Other-v0"] * 3 + [ENV] * 5, ["babyai-text@1"] * 8, episodes)
    assert other_env["all"] == 0.0  # states 1 and 2 were counted in another env only: other states


def test_data_coverage_reports_costs_and_what_the_cache_answers(trajectories, tmp_path, tiny_lm):
    cache = tmp_path / "ann"
    annotate_dataset(config(trajectories, cache, tiny_lm, limit=5))
    rows = measure_coverage(trajectories, cache=cache, histories=[0, 3], llm=LLMSpec(model=tiny_lm.spec.path, dtype="float32"))
    assert [r["history"] for r in rows] == [0, 3] and rows[0]["steps"] == rows[1]["steps"]
    assert rows[0]["distinct_states"] < rows[1]["distinct_states"]
    assert rows[0]["cached_states"] == 5 and rows[1]["cached_states"] == 0
    assert 0 < rows[0]["cached_step_share"] <= rows[0]["top_k_step_share"]["100"] <= 1
    held = rows[0]["heldout_top_k_step_share"]
    assert 0 <= held["100"] <= held["all"] <= 1 and held["all"] < rows[0]["top_k_step_share"]["10000"]
    out = ok("data", "coverage", trajectories, "--cache", cache, "--history", 0, "--model", tiny_lm.spec.path,
             "--dtype", "float32", "--json")
    assert json.loads(out)[0]["cached_states"] == 5
    table = runner.invoke(app, ["data", "coverage", str(trajectories), "--history", "0", "--history", "1",
                                "--model", tiny_lm.spec.path, "--dtype", "float32"]).output
    assert "| 0 |" in table and "| 1 |" in table and "top 1,000" in table and "new episodes" in table


def test_coverage_says_in_one_line_when_annotating_ahead_will_not_help():
    def row(history, found, episodes=40):
        return {"history": history, "steps": 2000, "episodes": episodes, "heldout_top_k_step_share": {"all": found}}

    assert ahead_warning([row(0, 0.77), row(3, 0.12)]) is None  # every history finds a real share
    lower = ahead_warning([row(0, 0.77), row(3, 0.004)])
    assert lower.startswith("warning: annotating ahead will not help at history 3") and "(history 3: 0.4%)" in lower
    assert "--history 0 (77% found)" in lower and "--live-budget" in lower and "\n" not in lower
    none = ahead_warning([row(0, 0.01), row(3, 0.0)])
    assert "history 0, 3" in none and "collect more steps" in none and "lower --history" in none
    assert ahead_warning([row(0, 0.0, episodes=1)]) is None  # nothing to hold out: no estimate, no warning


def test_data_coverage_warns_on_a_collection_a_run_will_not_meet(trajectories, tiny_lm):
    rows = measure_coverage(trajectories, histories=[3], llm=LLMSpec(model=tiny_lm.spec.path, dtype="float32"))
    assert rows[0]["episodes"] > 1 and rows[0]["heldout_top_k_step_share"]["all"] < 0.1  # history 3: all new
    out = ok("data", "coverage", trajectories, "--history", 3, "--model", tiny_lm.spec.path, "--dtype", "float32")
    warned = [line for line in out.splitlines() if line.startswith("warning: annotating ahead")]
    assert len(warned) == 1 and "--live-budget" in warned[0], out
    quiet = runner.invoke(app, ["data", "coverage", str(trajectories), "--history", "3", "--model", tiny_lm.spec.path,
                                "--dtype", "float32", "--json"])
    assert "warning" not in quiet.output and json.loads(quiet.output)[0]["history"] == 3


def test_cache_info_names_each_setup_with_the_options_that_select_it(trajectories, tmp_path, tiny_lm):
    cache = tmp_path / "ann"
    annotate_dataset(config(trajectories, cache, tiny_lm, limit=3))
    setups = json.loads(ok("cache", "info", cache, "--json"))["setups"]
    assert {u["task"] for u in setups} == {"action", "summary"} and all(u["entries"] == 3 for u in setups)
    assert all(u["model_options"] == f"--model {tiny_lm.spec.path} --dtype float32 --quant none" for u in setups)
    assert all(u["history_len"] == 0 and "shared" in u["layouts"] for u in setups)
    assert "| action | --model" in runner.invoke(app, ["cache", "info", str(cache)]).output


def test_sync_live_budget_goes_to_the_states_visited_most_over_the_run(tmp_path, tiny_lm):
    cache = AnnotationCache(tmp_path / "ann")
    annotator = Annotator(tiny_lm, cache, model=tiny_lm.spec.path, history_len=0, batch_size=4)
    live = SyncLive(annotator, AnnotationSetup(ENV, "babyai-text@1"), budget=1)
    targets = CachedTargets(cache, prompt_builder(lm=tiny_lm, history_len=0), calibration="sum", num_actions=3,
                            embedding_dim=tiny_lm.hidden_size, live=live)
    targets._count_visits([state(2)] * 5)  # earlier rollouts visited state 2 most
    got = targets.targets([state(1), state(1), state(2)])  # in this rollout state 1 comes first and twice
    assert got.mask.tolist() == [False, False, True]


def test_the_cache_refuses_a_run_of_another_setup_naming_what_differs(trajectories, tmp_path, tiny_lm):
    cache = tmp_path / "ann"
    annotate_dataset(config(trajectories, cache, tiny_lm, limit=3))
    ann = AnnotationCache(cache)
    llm = LLMSpec(model=tiny_lm.spec.path, dtype="float32")
    check_setup(ann, prompt_builder(lm=tiny_lm, history_len=0), llm=llm)
    with pytest.raises(CacheError, match=r"holds --history 0 annotations .*this run asks for --history 3"):
        check_setup(ann, prompt_builder(lm=tiny_lm, history_len=3), llm=llm)
    paper = prompt_builder(lm=tiny_lm, history_len=0, layout="paper")
    with pytest.raises(CacheError, match=r"holds no action annotations .*--layout shared.*asks for --layout paper"):
        check_setup(ann, paper, llm=llm)
    other = prompt_builder(lm=tiny_lm, history_len=0, model_fingerprint="f" * 64)
    with pytest.raises(CacheError, match=r"--dtype float32 --quant none annotations.*--new-setup"):
        check_setup(ann, other, llm=LLMSpec(model=tiny_lm.spec.path, dtype="bfloat16"))


def test_train_refuses_another_setup_in_one_line_and_new_setup_accepts_it(trajectories, tmp_path, tiny_lm):
    cache = tmp_path / "ann"
    annotate_dataset(config(trajectories, cache, tiny_lm, limit=3))
    train = ["train", "--env", ENV, "--cache", cache, "--model", tiny_lm.spec.path, "--dtype", "float32",
             "--num-envs", 2, "--num-steps", 16, "--frames", 32, "--live-budget", 0, "--history", 3]
    out = runner.invoke(app, [str(a) for a in [*train, "--out", tmp_path / "run"]])
    assert out.exit_code == 1 and "--history 0" in out.output and "--history 3" in out.output
    assert len(out.output.strip().splitlines()) == 1 and not (tmp_path / "run" / "checkpoint.pt").exists()
    ok(*train, "--out", tmp_path / "run", "--new-setup")
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert rows and all(r["charts/target_coverage"] == 0 for r in rows)  # the new setup: no cached target


def _wait(predicate, seconds: float = 120.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.2)
    return False


@pytest.mark.slow
def test_async_worker_rows_reach_a_later_rollout_and_a_killed_worker_leaves_the_run_going(tmp_path, tiny_lm):
    cache = AnnotationCache(tmp_path / "ann")
    spec = WorkerSpec(cache=str(cache.root), llm=LLMSpec(model=tiny_lm.spec.path, dtype="float32"),
                      setup=AnnotationSetup(ENV, "babyai-text@1", history_len=0), threads=1, batch_size=4, chunk=2)
    live = AsyncLive(spec, budget=6, max_restarts=1)
    targets = CachedTargets(cache, prompt_builder(lm=tiny_lm, history_len=0), calibration="sum", num_actions=3,
                            embedding_dim=tiny_lm.hidden_size, live=live)
    try:
        rollout = [state(k) for k in range(1, 7)] * 2
        first = targets.targets(rollout)  # the trainer never waits: nothing yet
        assert not first.mask.any() and targets.stats()["live_annotations"] == 0
        assert _wait(lambda: (AnnotationCache(cache.root).__len__() >= 12))
        later = targets.targets(rollout)  # a later rollout reads what the worker wrote to the shared cache
        assert later.mask.all() and np.isfinite(later.embeddings).all()
        assert targets.stats()["live_annotations"] == 6 and targets.stats()["live_queue"] == 0
        stats = targets.stats()
        assert 0 < stats["live_worker_startup_s"] < 120  # spawn, imports, the model loaded
        assert stats["live_worker_startup_s"] <= stats["live_first_answer_s"]  # its first shard, then on

        targets.targets([state(k) for k in range(10, 40)])  # more work; then the worker dies mid-run
        # Kill it as soon as it holds the work (the tiny model may finish 6 states between two polls, so
        # holding work is not asserted: a worker killed idle or mid-chunk must both leave the run going).
        _wait(lambda: live._queued.value > 0, 10)
        os.kill(live.process.pid, signal.SIGKILL)
        live.process.join(10)
        targets.targets([state(k) for k in range(40, 42)])  # the run goes on; the worker is restarted
        assert live.restarts == 1 and live.process.is_alive()
        assert verify(cache.root).ok
    finally:
        targets.close()
    assert live.exitcode is not None  # the worker ended with the run


@pytest.mark.slow
def test_a_worker_started_before_its_spec_answers_once_configured_and_one_never_configured_closes(tmp_path, tiny_lm):
    """`illm train` starts its worker before the run is configured: it preloads, then takes its spec."""
    llm = LLMSpec(model=tiny_lm.spec.path, dtype="float32")
    idle = AsyncLive(budget=4, early=llm)  # a run refused before it was configured: closed at once
    idle.close()
    idle.close()  # twice does nothing
    assert idle.exitcode is not None and idle.stats()["live_queue"] == 0
    cache = AnnotationCache(tmp_path / "ann")
    live = AsyncLive(budget=4, early=llm)
    live.configure(WorkerSpec(cache=str(cache.root), llm=llm, setup=AnnotationSetup(ENV, "babyai-text@1", history_len=0),
                              threads=1, batch_size=4, chunk=2), budget=3)
    try:
        live.submit([state(k) for k in range(1, 7)])  # the budget the run configured: 3 of them
        assert _wait(lambda: AnnotationCache(cache.root).__len__() >= 6)  # two tasks a state
        assert _wait(lambda: live._queued.value == 0 and live._done.value == 3)
        assert 0 < live.stats()["live_worker_startup_s"] <= live.stats()["live_first_answer_s"]
    finally:
        live.close()
    assert live.landed() == 3 and verify(cache.root).ok


@pytest.mark.slow
def test_train_with_async_live_annotation_logs_its_queue(tmp_path, tiny_lm):
    traj, cache = tmp_path / "traj", tmp_path / "ann"
    collect(CollectConfig(env_id=ENV, out=traj, steps=64, num_envs=4, seed=1))
    annotate_dataset(AnnotateConfig(data=traj, cache=cache, llm=LLMSpec(model=tiny_lm.spec.path, dtype="float32"), setup=PromptConfig(history_len=0),
                                    limit=4, batch_size=4))
    out = ok("train", "--env", ENV, "--cache", cache, "--model", tiny_lm.spec.path, "--dtype", "float32",
             "--history", 0, "--num-envs", 4, "--num-steps", 32, "--frames", 640, "--live-mode", "async",
             "--out", tmp_path / "run")
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 5 and all("charts/live_queue" in r for r in rows)
    assert "steps with an LLM target" in out and verify(cache).ok
    assert "--live-budget all" not in out  # a number: no promise of every step to take back


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_live_budget_all_with_async_says_before_it_starts_that_only_sync_promises_every_step(tmp_path):
    out = ok("train", "--env", ENV, "--method", "illm", "--backend", "oracle", "--history", 0, "--live-budget", "all",
             "--new-setup", "--cache", tmp_path / "ann", "--num-envs", 2, "--num-steps", 8, "--frames", 16,
             "--out", tmp_path / "run")
    said = [line for line in out.splitlines() if line.startswith("--live-budget all")]
    assert len(said) == 1 and "--live-mode sync" in said[0]
