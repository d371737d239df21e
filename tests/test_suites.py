"""The suite seam: a fifth suite is one file plus one registry entry (here a tiny one registered from
this test file runs through collect, the env pool and the unchanged trainer), and every shipped
suite's contract (ids, observation spec, text, options, score)."""

from __future__ import annotations

import numpy as np
import pytest

from illm_tools.collect import CollectConfig, collect
from illm_tools.data.trajectories import open_table
from illm_tools.envs import SUITES, known_env_ids, make_env, register_suite, renderer_of, suite_of
from illm_tools.envs.pool import EnvPool
from illm_tools.errors import UnknownEnvError, UsageError
from illm_tools.rl import TrainConfig, Trainer, make_pool
from illm_tools.rl.checkpoint import load_checkpoint
from fakes import TINY, TinySuite




@pytest.fixture
def tiny():
    register_suite(TinySuite())
    try:
        yield
    finally:
        del SUITES["tiny"]


def test_a_suite_registered_from_a_test_file_runs_every_stage(tiny, tmp_path):
    assert suite_of(TINY).name == "tiny" and TINY in known_env_ids() and renderer_of(TINY) == "tiny-text@1"
    with pytest.raises(UsageError, match="already registered"):
        register_suite(TinySuite())
    with pytest.raises(UsageError, match="takes no env option width; it takes length"):
        make_env(TINY, width=3)

    summary = collect(CollectConfig(env_id=TINY, out=tmp_path / "traj", steps=60, num_envs=3,
                                    env_options={"length": 4}))
    assert summary["rows"] == 60 and summary["episodes_finished"] > 0 and summary["success_rate"] == 1.0
    table = open_table(tmp_path / "traj")
    assert set(table["renderer"].to_pylist()) == {"tiny-text@1"}
    assert table["obs_text"][0].as_py().startswith("You are ") and table["valid_actions"][0].as_py() == ["go left", "go right"]

    for method in ("ppo", "rnd"):
        cfg = TrainConfig(env_id=TINY, method=method, run_dir=tmp_path / method, total_steps=64, num_envs=2,
                          num_steps=16, tensorboard=False, env_options={"length": 4})
        pool = make_pool(cfg)
        try:
            last = Trainer(cfg.resolved(), pool).train()
        finally:
            pool.close()
        assert last["global_step"] == 64 and last["charts/score"] == 1.0  # every finished episode succeeded
        assert load_checkpoint(tmp_path / method)["action_names"] == ["go left", "go right"]


def test_pool_seeds_are_deterministic_per_episode(tiny):
    def positions(pool, steps):
        out = [pool.reset().images[:, :, 3, 0].argmax(1).tolist()]
        for _ in range(steps):
            out.append(pool.step(np.ones(pool.num_envs, np.int64)).obs.images[:, :, 3, 0].argmax(1).tolist())
        return out

    a, b = EnvPool(TINY, 3, seed=5), EnvPool(TINY, 3, seed=5)
    assert positions(a, 12) == positions(b, 12)
    step = a.step(np.ones(3, np.int64))
    assert all(s >= 5 for s in step.obs.seeds)


def test_unknown_env_and_suite_specific_options_are_refused():
    with pytest.raises(UnknownEnvError, match="did you mean ALE/MontezumaRevenge-v5"):
        suite_of("ALE/MontezumaRevenge-v4x")
    with pytest.raises(UsageError, match="takes no env option area"):
        make_env("ALE/Pong-v5", area=3)
    with pytest.raises(UsageError, match="no text observation"):
        renderer_of("ALE/Pong-v5")
    with pytest.raises(UsageError, match="has no action space 'original'"):
        make_env("ALE/Pong-v5", action_space="original")


@pytest.mark.parametrize("env_id,kind,score", [
    ("BabyAI-GoToLocal-v0", "grid", "success rate"),
    ("MiniGrid-MultiRoom-N6-v0", "grid", "success rate"),
    ("MiniHack-River-Monster-v0", "glyphs", "success rate"),
    ("CrafterReward-v1", "image", "Crafter score"),
    ("CrafterReward-Semantic-v1", "cells", "Crafter score"),
    ("ALE/MontezumaRevenge-v5", "frames", "mean return"),
])
def test_every_suite_gives_its_policy_array_text_and_score(env_id, kind, score):
    suite = suite_of(env_id)
    spec = suite.obs_spec(env_id)
    assert spec.kind == kind and suite.score_name == score
    pool = EnvPool(env_id, 2, seed=0, vector="sync")
    try:
        obs = pool.reset()
        assert obs.images.shape == (2, *spec.shape) and obs.images.dtype == np.dtype(spec.dtype)
        assert (obs.texts[0] != "") == (suite.renderer is not None)
        step = pool.step(np.zeros(2, np.int64))
        assert step.obs.images.shape == obs.images.shape and len(pool.action_names) == len(set(pool.action_names))
    finally:
        pool.close()


@pytest.mark.parametrize("env_id", ["MiniHack-River-Monster-v0", "MiniHack-MultiRoom-N4-Monster-v0",
                                    pytest.param("CrafterReward-v1", marks=pytest.mark.slow)])  # Crafter: 15 s
def test_a_seed_gives_the_same_episodes(env_id):
    def texts(pool):
        out, rng = [pool.reset().texts], np.random.default_rng(0)
        for _ in range(25):
            out.append(pool.step(rng.integers(0, len(pool.action_names), 2)).obs.texts)
        pool.close()
        return out

    first = texts(EnvPool(env_id, 2, seed=3, vector="sync"))
    assert first == texts(EnvPool(env_id, 2, seed=3, vector="sync"))
    assert first[0] != texts(EnvPool(env_id, 2, seed=4, vector="sync"))[0]


def test_a_minihack_task_takes_minihacks_reward_options():
    """Every MiniHack task hands its `**kwargs` on to MiniHack's base class, whose reward options are the
    suite's too: a death that costs (`reward_lose`) reaches the env, and an unknown option is still refused."""
    env = make_env("MiniHack-LavaCross-Levitate-Ring-Pickup-Restricted-v0", reward_lose=-1.0, penalty_step=0.0)
    try:
        base = env.env.unwrapped
        assert (base.reward_lose, base.penalty_step) == (-1.0, 0.0)
    finally:
        env.close()
    with pytest.raises(UsageError, match="takes no env option reward_loose; it takes .*reward_lose"):
        make_env("MiniHack-MultiRoom-N4-Monster-v0", reward_loose=-1.0)
