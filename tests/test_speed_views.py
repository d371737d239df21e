"""Issue 70's speed fixes on MiniHack and Crafter: Crafter's semantic view (its ids ending
-Semantic-v1: what the picture shows as cell codes, no picture drawn), read by network "frame"'s
cell torso and the bonuses' "cells" adapter; numba compiling Crafter's world generator without
changing the world; GlyphNet's features computed once per distinct row with the same outputs and
gradients. Speed itself is measured by benchmarks/train.py's levels form (docs/measured.md), not here."""

from __future__ import annotations

import os
import subprocess
import sys

import crafter
import numpy as np
import pytest
import torch

from illm_tools.envs import make_env, suite_of
from illm_tools.envs.crafter import OBJECT_TEXTURES, SEMANTIC_PARTS
from illm_tools.envs.pool import EnvPool
from illm_tools.errors import UnknownEnvError, UsageError
from illm_tools.intrinsic.registry import get_method
from illm_tools.rl.networks import FrameNet, GlyphNet, GridMissionNet, make_network, once_per_distinct

SEMANTIC = "CrafterReward-Semantic-v1"


def _crafter_semantic_map(env) -> np.ndarray:
    """crafter's own semantic map (materials, objects over them by type), [x, y] like the world."""
    types = [crafter.objects.Player, crafter.objects.Cow, crafter.objects.Zombie, crafter.objects.Skeleton,
             crafter.objects.Arrow, crafter.objects.Plant]
    return crafter.engine.SemanticView(env._world, types)()


def test_the_semantic_view_is_what_the_picture_shows_as_codes_and_draws_no_picture(monkeypatch):
    def no_picture(*_, **__):
        raise AssertionError("the semantic view drew the picture")

    monkeypatch.setattr(crafter.Env, "render", no_picture)
    env = make_env(SEMANTIC, render_text=False)
    spec = suite_of(SEMANTIC).obs_spec(SEMANTIC)
    obs, _ = env.reset(seed=3)
    assert spec.kind == "cells" and obs.shape == spec.shape == (143,) and obs.dtype == np.uint8
    assert list(spec.parts) == ["materials", "objects", "inventory", "daylight"]
    assert sum(int(np.prod(s)) for s in spec.parts.values()) == 143 == env.observation_space.shape[0]
    assert obs[126:142].tolist() == [9, 9, 9, 9] + [0] * 12  # health, food, drink, energy full; no items
    rng = np.random.default_rng(0)
    for _ in range(40):
        obs, *_ = env.step(int(rng.integers(17)))
        inner = env._env
        px, py = (int(v) for v in inner._player.pos)
        window = _crafter_semantic_map(inner)[px - 4:px + 5, py - 3:py + 4].T  # rows north to south, as drawn
        materials, objects = (obs[:63].reshape(SEMANTIC_PARTS["materials"]), obs[63:126].reshape(7, 9))
        assert np.array_equal(np.where(objects == 0, materials, window), window)  # materials where no object
        assert OBJECT_TEXTURES[objects[3, 4] - 1] == inner._player.texture  # the player, facing as drawn
        assert obs[126:142].tolist() == [max(v, 0) for v in inner._player.inventory.values()]
        assert 0 <= obs[142] <= 9


def test_the_semantic_view_at_the_worlds_edge_reads_nothing_past_it():
    env = make_env(SEMANTIC, render_text=False)
    env.reset(seed=0)
    env._env._world.move(env._env._player, (0, 32))  # the west edge: the view's 4 western columns lie outside
    obs = env._env._obs()
    materials = obs[:63].reshape(7, 9)
    assert (materials[:, :4] == 0).all() and (materials[:, 4:] > 0).all()


def test_the_semantic_ids_refuse_picture_options_and_a_misspelt_id_in_one_line():
    with pytest.raises(UsageError) as err:
        make_env(SEMANTIC, size=32)
    assert "\n" not in str(err.value) and "takes no env option size" in str(err.value) and "area, length" in str(err.value)
    with pytest.raises(UsageError, match="takes no env option noisy_tv"):
        make_env("CrafterNoReward-Semantic-v1", noisy_tv=0.1)
    with pytest.raises(UnknownEnvError) as err:
        suite_of("CrafterReward-Semantik-v1")
    assert "\n" not in str(err.value) and "did you mean CrafterReward-Semantic-v1" in str(err.value)
    assert suite_of("CrafterReward-v1").obs_spec("CrafterReward-v1").kind == "image"  # the pixel view stays the default


def test_the_semantic_view_trains_through_the_frame_network_and_the_bonus_encoders():
    pool = EnvPool(SEMANTIC, 2, seed=0, vector="sync")
    try:
        images = torch.as_tensor(pool.reset().images)
        assert images.shape == (2, 143)
        suite = suite_of(SEMANTIC)
        net = make_network(get_method("ppo"), SEMANTIC, len(pool.action_names), image_shape=(143,), vocab_size=10,
                           network_options={}, embedding_dim=None, head_hidden=64)
        assert type(net) is FrameNet and net.feature_dim == 16 * 63 + 8 * 17
        out = net(images, torch.zeros(2, 4, dtype=torch.long))
        assert out.logits.shape == (2, 17) and torch.isfinite(out.logits).all()
        observation = suite.observation(SEMANTIC)
        assert observation.encoder(32, 8)(images).shape == (2, 8) and not observation.rnd_picture
        assert np.array_equal(suite.hop_input(pool.reset().images[0]), pool.reset().images[0])  # codes, no grey
    finally:
        pool.close()


def test_numba_compiles_the_world_generator_and_the_worlds_are_the_same():
    """numba is a dependency (pyproject.toml): opensimplex's noise compiles, and the worlds it makes
    are pure Python's, bit for bit."""
    import numba  # noqa: F401
    from opensimplex import internals

    assert type(internals._noise3).__module__.startswith("numba")
    code = ("import crafter, hashlib; e = crafter.Env(seed=5); e.reset(); "
            "print(hashlib.sha256(e._world._mat_map.tobytes()).hexdigest())")
    worlds = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                             env={**os.environ, "NUMBA_DISABLE_JIT": jit}, check=True).stdout for jit in ("0", "1")]
    assert worlds[0] == worlds[1] and len(worlds[0].strip()) == 64


def test_glyph_features_once_per_distinct_row_match_every_row():
    """GlyphNet's crop and message features, and its whole forward, over a minibatch with repeats:
    the same outputs and gradients as computed on every row."""
    env_id = "MiniHack-Room-5x5-v0"
    torch.manual_seed(0)
    net = GlyphNet(8, vocab_size=10, observation=suite_of(env_id).observation(env_id), image_shape=(337,))
    rng = np.random.default_rng(0)
    rows = np.zeros((40, 337), np.int16)
    rows[:, :81] = rng.choice([2359, 2371, 2378, 337], size=(40, 81))
    rows[:5, 81:90] = rng.integers(32, 120, size=(5, 9))
    x = torch.as_tensor(rows[rng.integers(0, 40, size=512)])  # 512 rows, at most 40 distinct
    missions = torch.zeros(512, 4, dtype=torch.long)

    def run(distinct: bool):
        net.zero_grad()
        if distinct:
            features = net.features(x, missions)
        else:
            cells = 81
            features = torch.cat([net._crop(x[:, :cells]), net._message(x[:, cells:])], dim=1)
        (features.square().sum() + features.sum()).backward()
        return features.detach(), [p.grad.clone() for p in net.parameters() if p.grad is not None]

    (f1, g1), (f0, g0) = run(True), run(False)
    torch.testing.assert_close(f1, f0, rtol=1e-5, atol=1e-5)
    assert len(g1) == len(g0)
    for a, b in zip(g1, g0):  # float32 sums in another order: close against the gradient's size, not per element
        assert float((a - b).norm() / b.norm()) < 1e-4
    # the whole forward once per distinct (observation, mission) row: the same outputs and gradients
    def forward(distinct: bool):
        net.zero_grad()
        out = net(x, missions) if distinct else GridMissionNet.forward(net, x, missions)
        (out.logits.logsumexp(-1).sum() + out.value_ext.square().sum() + out.features.sum()).backward()
        return [t.detach() for t in out], [p.grad.clone() for p in net.parameters() if p.grad is not None]

    (o1, g1), (o0, g0) = forward(True), forward(False)
    for a, b in zip(o1, o0):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    for a, b in zip(g1, g0):
        assert float((a - b).norm() / b.norm().clamp_min(1e-12)) < 1e-4
    # a rollout step's few rows, and rows that are all distinct, take the plain path
    calls = []
    once_per_distinct(lambda r: calls.append(len(r)) or r.float(), x[:16])
    once_per_distinct(lambda r: calls.append(len(r)) or r.float(), torch.arange(512 * 2).view(512, 2).to(torch.int16))
    assert calls == [16, 512]
