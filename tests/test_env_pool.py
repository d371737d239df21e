"""EnvPool: determinism, episode seeds, same-step autoreset and episode statistics."""
from __future__ import annotations

import numpy as np
import pytest

from illm_tools.envs import make_env
from illm_tools.envs.pool import EnvPool
from illm_tools.errors import UsageError

ENV = "BabyAI-GoToLocal-v0"


def _run(pool: EnvPool, steps: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    history = [pool.reset()]
    results = []
    for _ in range(steps):
        results.append(pool.step(rng.integers(0, len(pool.action_names), pool.num_envs)))
        history.append(results[-1].obs)
    return history, results


def test_reset_shapes_and_dtypes():
    pool = EnvPool(ENV, 3, seed=10)
    obs = pool.reset()
    assert obs.images.shape == (3, 7, 7, 3) and obs.images.dtype == np.uint8
    assert obs.seeds.tolist() == [10, 11, 12] and obs.steps.tolist() == [0, 0, 0]
    assert all(t.startswith("You see") for t in obs.texts) and all(obs.missions)
    assert pool.action_names == ("turn left", "turn right", "go forward")  # GoTo: the paper's 3 actions


def test_same_seed_same_episodes():
    a, _ = _run(EnvPool(ENV, 4, seed=7), 40)
    b, _ = _run(EnvPool(ENV, 4, seed=7), 40)
    assert [o.texts for o in a] == [o.texts for o in b]
    assert all(np.array_equal(x.images, y.images) for x, y in zip(a, b))
    c, _ = _run(EnvPool(ENV, 4, seed=8), 1)
    assert c[0].texts != a[0].texts


def test_env_matches_a_single_env_with_the_same_seed():
    pool = EnvPool(ENV, 2, seed=3)
    obs = pool.reset()
    env = make_env(ENV)
    _, info = env.reset(seed=4)
    assert obs.texts[1] == info["text"] and obs.missions[1] == info["mission"]


def test_same_step_autoreset_and_episode_stats():
    pool = EnvPool(ENV, 4, seed=0, action_space="irrelevant")
    pool.reset()
    limit = pool.envs.envs[0].unwrapped.max_steps
    assert limit > 0
    seeds_seen = set(range(4))
    finished = []
    for t in range(1, 2 * limit + 1):
        result = pool.step(np.full(4, 7))  # "do nothing": every episode runs into the time limit
        if t % limit:
            assert not result.episodes and result.obs.steps.tolist() == [t % limit] * 4
            continue
        assert result.truncated.all() and not result.terminated.any()
        assert result.obs.steps.tolist() == [0, 0, 0, 0]  # already the new episodes' first states
        k = t // limit
        assert result.obs.seeds.tolist() == [k * 4 + i for i in range(4)]
        assert not seeds_seen & set(result.obs.seeds.tolist())
        seeds_seen |= set(result.obs.seeds.tolist())
        finished += result.episodes
        for i in range(4):
            fresh = make_env(ENV)
            _, info = fresh.reset(seed=int(result.obs.seeds[i]))
            assert result.obs.texts[i] == info["text"]
    assert [(e.env_index, e.episode_return, e.length, e.success) for e in finished] == \
        [(i, 0.0, limit, False) for i in range(4)] * 2


def test_success_counts_terminated_with_reward():
    _, results = _run(EnvPool(ENV, 8, seed=0, num_dists=1), 300)
    episodes = [e for r in results for e in r.episodes]
    assert any(e.success for e in episodes)  # random walks find the goal with one distractor
    for r in results:
        for i, ret, length, success, _info in r.episodes:
            assert r.terminated[i] or r.truncated[i]
            assert success == bool(r.terminated[i] and r.rewards[i] > 0)
            assert length >= 1 and (ret > 0) == (r.rewards[i] > 0)


def test_render_false_skips_text_only():
    with_text, _ = _run(EnvPool(ENV, 3, seed=5), 20)
    without, _ = _run(EnvPool(ENV, 3, seed=5, render=False), 20)
    assert all(t == "" for o in without for t in o.texts)
    assert all(np.array_equal(x.images, y.images) and x.missions == y.missions
               for x, y in zip(with_text, without))


def test_pool_records_the_resolved_action_space():
    pool = EnvPool(ENV, 2, seed=0, render=False)
    assert pool.action_space_name == "original" and pool.action_names == ("turn left", "turn right", "go forward")
    assert pool.envs.get_attr("action_names")[0] == pool.action_names
    assert EnvPool("BabyAI-PickupLoc-v0", 1, seed=0, render=False).action_space_name == "augmented"
    assert EnvPool(ENV, 1, seed=0, render=False, action_space="irrelevant").action_space_name == "irrelevant"


def test_usage_errors():
    pool = EnvPool(ENV, 2, seed=0)
    with pytest.raises(UsageError, match="before reset"):
        pool.step(np.zeros(2, dtype=np.int64))
    pool.reset()
    with pytest.raises(UsageError, match="expected 2 actions"):
        pool.step(np.zeros(3, dtype=np.int64))
    with pytest.raises(UsageError):
        EnvPool(ENV, 0, seed=0)


def test_a_seed_list_fixes_the_layouts_every_env_cycles_through():
    """--env-seeds: episode k of env i takes seeds[(i + k * num_envs) % len(seeds)]; one seed is one
    MultiRoom map for every episode (paper Figure 1's heatmap of one map)."""
    pool = EnvPool("MiniGrid-MultiRoom-N6-v0", 3, seed=100, episode_seeds=(7,), render=False)
    first = pool.reset()
    assert first.seeds.tolist() == [7, 7, 7]
    assert pool.episode_seed(2, 5) == 7
    grids = {tuple(map(tuple, pool.envs.envs[i].unwrapped.grid.encode()[:, :, 0])) for i in range(3)}
    assert len(grids) == 1  # the same layout in every env
    seen, rng = set(), np.random.default_rng(0)
    for _ in range(300):
        seen.update(pool.step(rng.integers(0, 3, size=3)).obs.seeds.tolist())
    assert seen == {7}
    pool.close()
    two = EnvPool("BabyAI-GoToLocal-v0", 2, seed=0, episode_seeds=(4, 9), render=False)
    assert [two.episode_seed(i, k) for k in range(2) for i in range(2)] == [4, 9, 4, 9]
    two.close()
    from illm_tools.rl.config import TrainConfig

    assert TrainConfig.from_dict(dict(env_seeds="3, 5")).env_seeds == (3, 5)
    with pytest.raises(UsageError, match="--env-seeds takes whole numbers"):
        TrainConfig(env_seeds="a")
