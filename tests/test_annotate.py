"""The annotation pipeline on a tiny random model: the shared-prefix path equals the separate
paths, each distinct key is annotated once, a killed run resumes without losing or redoing work,
two writers share a cache, and the trainer's keys and live fallback meet `illm annotate`'s rows."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest

from conftest import collect_babyai
from illm_tools.tasks.annotation_setup import AnnotationSetup
from illm_tools.llm.spec import LLMSpec
from illm_tools.annotate.bulk import AnnotateConfig, annotate_dataset
from illm_tools.cache.store import AnnotationCache
from illm_tools.cache.verify import verify
from illm_tools.collect import RandomPolicy
from illm_tools.llm.driver import generate, score_and_generate, score_candidates
from illm_tools.rl.live import SyncLive
from illm_tools.tasks.prompts import PromptBuilder
from illm_tools.tasks.state import HistoryTracker, StateRecord

ENV = "BabyAI-GoToLocal-v0"
ACTIONS = ("turn left", "turn right", "go forward", "pick up", "drop", "toggle")


pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")


@pytest.fixture(scope="module")
def trajectories(tmp_path_factory):
    return collect_babyai(tmp_path_factory, steps=48, seed=5, action_space="augmented")


def config(trajectories, cache, tiny_lm, **kw) -> AnnotateConfig:
    return AnnotateConfig(data=trajectories, cache=cache, llm=LLMSpec(model=tiny_lm.spec.path, dtype="float32"),
                          batch_size=4, chunk=8, **kw)


def test_shared_prefix_equals_separate_paths(tiny_lm):
    b = PromptBuilder(env_id=ENV, renderer="babyai-text@1", model_fingerprint="x", model="tiny", layout="shared")
    records = [StateRecord("go to the red ball", (("You see a wall 2 steps forward", "turn left"),) * k,
                           f"You see a red ball {k + 1} steps forward", ACTIONS) for k in range(4)]
    action = [b.render("action", r) for r in records]
    summary = [b.render("summary", r) for r in records]
    joint_scores, joint_gens = score_and_generate(tiny_lm, [p.text for p in action], [list(p.candidates) for p in action],
                                                  [p.text for p in summary], max_new_tokens=8, batch_size=3)
    scores = score_candidates(tiny_lm, [p.text for p in action], [list(p.candidates) for p in action])
    gens = generate(tiny_lm, [p.text for p in summary], max_new_tokens=8)
    for js, s in zip(joint_scores, scores):
        assert np.allclose(js.sums, s.sums, atol=1e-4)
        assert js.token_counts == s.token_counts
    for jg, g in zip(joint_gens, gens):
        assert jg.token_ids == g.token_ids
        assert np.allclose(jg.embedding, g.embedding, atol=1e-4)


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_annotate_writes_each_distinct_key_once(trajectories, tmp_path, tiny_lm):
    cache = tmp_path / "ann"
    stats = annotate_dataset(config(trajectories, cache, tiny_lm)).stats
    assert stats.misses == stats.keys and stats.annotated_states == stats.states
    ann = AnnotationCache(cache)
    assert len(ann) == stats.keys == 2 * stats.states
    assert ann.tasks() == {"action": stats.states, "summary": stats.states}
    import pyarrow as pa
    import json

    shard = cache / json.loads((cache / "manifest.json").read_text())["shards"][0]["name"]
    keys = pa.ipc.open_stream(pa.BufferReader(shard.read_bytes())).read_all().column("key").to_pylist()
    row = next(r for r in ann.lookup(keys).values() if r["task"] == "action")
    assert row["candidates"] == list(ACTIONS) and len(row["neutral_logprob_sum"]) == 6
    assert row["chosen_index"] == int(np.argmax(row["cand_logprob_sum"]))
    again = annotate_dataset(config(trajectories, cache, tiny_lm)).stats
    assert again.hits == again.keys and again.annotated_states == 0 and len(AnnotationCache(cache)) == len(ann)


@pytest.mark.slow
def test_killed_run_resumes_with_only_what_is_missing(trajectories, tmp_path, tiny_lm, monkeypatch):
    cache = tmp_path / "ann"
    writes = []
    real_write = AnnotationCache.write

    def dying_write(self, rows):
        if len(writes) == 2:
            raise KeyboardInterrupt  # killed during the third chunk
        writes.append(len(rows))
        return real_write(self, rows)

    monkeypatch.setattr(AnnotationCache, "write", dying_write)
    with pytest.raises(KeyboardInterrupt):
        annotate_dataset(config(trajectories, cache, tiny_lm))
    monkeypatch.setattr(AnnotationCache, "write", real_write)
    kept = len(AnnotationCache(cache))
    assert kept == sum(writes) > 0
    resumed = annotate_dataset(config(trajectories, cache, tiny_lm)).stats
    assert resumed.hits == kept and resumed.rows == resumed.keys - kept
    assert verify(cache).ok and len(AnnotationCache(cache)) == resumed.keys


def _annotate_in_process(args):
    trajectories, cache, model, cache_dir = args
    import os

    os.environ["ILLM_CACHE_DIR"] = cache_dir
    stats = annotate_dataset(AnnotateConfig(data=trajectories, cache=cache, llm=LLMSpec(model=model, dtype="float32"),
                                            batch_size=4, chunk=4)).stats
    return stats.keys


@pytest.mark.slow  # two spawned processes each import torch and transformers: 30-40 s here
def test_two_annotate_processes_share_a_cache(trajectories, tmp_path, tiny_lm):
    cache = tmp_path / "ann"
    args = (str(trajectories), str(cache), tiny_lm.spec.path, str(tmp_path / "illm-cache"))
    with mp.get_context("spawn").Pool(2) as pool:
        keys = pool.map(_annotate_in_process, [args, args])
    report = verify(cache)
    assert report.ok and report.keys == report.rows == keys[0] == keys[1]


@pytest.mark.slow
def test_trainer_keys_hit_the_rows_annotate_wrote_and_live_fallback_writes_back(trajectories, tmp_path, tiny_lm):
    from illm_tools.annotate.engine import Annotator
    from illm_tools.envs.pool import EnvPool
    from illm_tools.rl.targets import CachedTargets

    cache = tmp_path / "ann"
    annotate_dataset(config(trajectories, cache, tiny_lm))
    # replay the collection (same seeds, same random policy) the way the trainer sees it
    pool = EnvPool(ENV, 4, 5, action_space="augmented")
    policy = RandomPolicy(len(pool.action_names), 5)
    tracker = HistoryTracker(4, 3, pool.action_names)
    obs, records = pool.reset(), []
    for _ in range(12):
        records += tracker.records(obs.missions, obs.texts)
        actions = policy.act(obs)
        step = pool.step(actions)
        tracker.push(obs.texts, actions, np.logical_or(step.terminated, step.truncated))
        obs = step.obs
    ann = AnnotationCache(cache)
    annotator = Annotator(tiny_lm, ann, model=tiny_lm.spec.path, batch_size=4)
    builder = annotator.builder(ENV, "babyai-text@1")
    cached = CachedTargets(ann, builder, calibration="pmi", num_actions=6, embedding_dim=tiny_lm.hidden_size)
    targets = cached.targets(records)
    assert targets.mask.all() and cached.stats()["cache_hit_rate"] == 1.0
    assert np.allclose(targets.action_probs.sum(1), 1.0) and np.isfinite(targets.embeddings).all()

    # states the cache has never seen: the live fallback annotates at most the budget, writes back
    unseen = [StateRecord("go to the purple key", (), f"You see a purple key {k} steps forward", ACTIONS)
              for k in range(1, 6)]
    live = CachedTargets(ann, builder, calibration="sum", num_actions=6, embedding_dim=tiny_lm.hidden_size,
                         live=SyncLive(annotator, AnnotationSetup(ENV, "babyai-text@1"), budget=3))
    first = live.targets(unseen + unseen[:1])
    assert first.mask.tolist() == [True, True, True, False, False, True]
    assert live.stats()["live_annotations"] == 3
    reread = AnnotationCache(cache)
    assert reread.contains(live.keys(unseen[:3])["action"]).all() and verify(cache).ok
