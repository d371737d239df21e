"""The noisy TV (paper Table 4) changes only its patch, with noise a seed repeats; MiniGrid runs
count visits per cell (Figure 1), keep counting across a resume, and the heatmap is a PNG."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from illm_tools.envs import make_env
from illm_tools.envs.noisy_tv import NoisyTV
from illm_tools.errors import UsageError
from illm_tools.rl.visitation import FILE, VisitCounts, heatmap_png


class Still(gym.Env):
    """A constant observation of the given shape."""

    def __init__(self, shape):
        self.observation_space = gym.spaces.Box(0, 255, shape, np.uint8)
        self.action_space = gym.spaces.Discrete(1)
        self.frame = (np.arange(np.prod(shape)) % 200).astype(np.uint8).reshape(shape)

    def reset(self, *, seed=None, options=None):
        return self.frame.copy(), {}

    def step(self, action):
        return self.frame.copy(), 0.0, False, False, {}


@pytest.mark.parametrize("shape", [(84, 84), (64, 64, 3)])
def test_the_noisy_tv_changes_only_the_lower_right_patch(shape):
    plain = Still(shape).frame
    assert np.array_equal(NoisyTV(Still(shape), 0.0).reset(seed=1)[0], plain)
    env = NoisyTV(Still(shape), 1.0)
    obs, _ = env.reset(seed=1)
    steps = [obs] + [env.step(0)[0] for _ in range(3)]
    for o in steps:
        assert np.array_equal(o[:-32], plain[:-32]) and np.array_equal(o[:, :-32], plain[:, :-32])
        assert not np.array_equal(o[-32:, -32:], plain[-32:, -32:])
    again = NoisyTV(Still(shape), 1.0)
    assert np.array_equal(again.reset(seed=1)[0], steps[0]) and np.array_equal(again.step(0)[0], steps[1])
    assert not np.array_equal(NoisyTV(Still(shape), 1.0).reset(seed=2)[0], steps[0])
    half = NoisyTV(Still(shape), 0.5)
    half.reset(seed=0)
    noised = [not np.array_equal(half.step(0)[0], plain) for _ in range(200)]
    assert 60 < sum(noised) < 140
    with pytest.raises(UsageError, match=r"in \[0, 1\]"):
        NoisyTV(Still(shape), 1.5)


@pytest.mark.parametrize("env_id", ["ALE/Pong-v5", "CrafterReward-v1"])
def test_noisy_tv_as_an_env_option(env_id):
    clean, noisy = make_env(env_id, render_text=False), make_env(env_id, render_text=False, noisy_tv=1.0)
    a, b = clean.reset(seed=3)[0], noisy.reset(seed=3)[0]
    newest = (lambda o: o[-1]) if a.ndim == 3 and a.shape[0] == 4 else (lambda o: o)
    assert np.array_equal(newest(a)[:-32], newest(b)[:-32]) and np.array_equal(newest(a)[:, :-32], newest(b)[:, :-32])
    assert not np.array_equal(newest(a)[-32:, -32:], newest(b)[-32:, -32:])
    with pytest.raises(UsageError, match="noisy_tv"):
        make_env("BabyAI-GoToLocal-v0", noisy_tv=0.5)


def test_visit_counts_grow_save_load_and_draw(tmp_path):
    visits = VisitCounts()
    visits.add(np.array([[1, 2], [1, 2], [3, 0], [-1, -1]]))
    assert visits.counts.shape == (3, 4) and visits.counts[2, 1] == 2 and visits.counts[0, 3] == 1
    visits.add(np.array([[5, 6]]))
    assert visits.counts.shape == (7, 6) and visits.counts.sum() == 4
    visits.save(tmp_path)
    assert np.array_equal(VisitCounts.load(tmp_path).counts, visits.counts)
    restored = VisitCounts()
    restored.load_state_dict(visits.state_dict())
    assert np.array_equal(restored.counts, visits.counts) and VisitCounts.load(tmp_path / "none").counts.size == 0
    png = heatmap_png(visits.counts, tmp_path / "heat.png", title="test")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_minigrid_run_counts_visits_and_a_resume_keeps_counting(tmp_path):
    from illm_tools.rl import TrainConfig
    from illm_tools.rl.run import train

    info = make_env("MiniGrid-MultiRoom-N6-v0").reset(seed=0)[1]
    assert info["agent_pos"].shape == (2,) and tuple(info["grid_size"]) == (25, 25)
    common = dict(env_id="MiniGrid-MultiRoom-N6-v0", method="ppo", run_dir=tmp_path / "run", num_envs=2, num_steps=16,
                  tensorboard=False, num_minibatches=2)
    train(TrainConfig.from_dict(dict(total_steps=32, **common)))
    first = np.load(tmp_path / "run" / FILE)
    assert first.sum() == 32 + 2  # every step's new state, and the first states
    train(TrainConfig.from_dict(dict(total_steps=64, resume=True, **common)))
    assert np.load(tmp_path / "run" / FILE).sum() == 64 + 2  # counting goes on from the checkpoint
