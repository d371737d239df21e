"""PPO trainer: GAE, modes, metrics, checkpoint and resume (the bonus reaching the loss, for every method:
tests/test_methods.py)."""

import json

import numpy as np
import pytest
import torch

from illm_tools.errors import OutputExistsError, UsageError
from illm_tools.llm.spec import LLMSpec
from illm_tools.rl import TrainConfig, Trainer, gae, load_checkpoint, load_policy, make_pool

from fakes import ACTIONS, FakePool, FakeProvider, RefusingProvider, make_trainer  # noqa: F401

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_gae_matches_a_direct_computation():
    g = torch.Generator().manual_seed(0)
    rewards, values = torch.rand(5, 2, generator=g), torch.rand(5, 2, generator=g)
    ends = torch.tensor([[0, 0], [1, 0], [0, 0], [0, 1], [0, 0]], dtype=torch.float32)
    next_value, gamma, lam = torch.tensor([0.3, 0.7]), 0.9, 0.8
    adv, ret = gae(rewards, values, next_value, ends, gamma, lam)
    for n in range(2):
        v = torch.cat([values[:, n], next_value[n:n + 1]])
        for t in range(5):
            expected, discount = 0.0, 1.0
            for k in range(t, 5):
                delta = rewards[k, n] + gamma * v[k + 1] * (1 - ends[k, n]) - v[k]
                expected += discount * delta
                if ends[k, n]:
                    break
                discount *= gamma * lam
            assert adv[t, n].item() == pytest.approx(float(expected), abs=1e-5)
    assert torch.allclose(ret, adv + values)


def test_gae_of_stacked_streams_is_each_streams_own_bit_for_bit():
    """Two streams in one loop (the trainer's extrinsic and intrinsic advantages) give exactly what a
    call per stream gives, each with its own gamma."""
    g = torch.Generator().manual_seed(0)
    rewards, values = torch.randn(64, 8, 2, generator=g), torch.randn(64, 8, 2, generator=g)
    ends = (torch.rand(64, 8, 2, generator=g) < 0.1).float()
    next_value = torch.randn(8, 2, generator=g)
    adv, ret = gae(rewards, values, next_value, ends, (0.99, 0.999), 0.95)
    for s, gamma in enumerate((0.99, 0.999)):
        own = gae(rewards[..., s], values[..., s], next_value[:, s], ends[..., s], gamma, 0.95)
        assert torch.equal(adv[..., s], own[0]) and torch.equal(ret[..., s], own[1])


def test_ppo_mode_has_no_intrinsic_reward_and_no_head_loss(tmp_path):
    trainer, _ = make_trainer(tmp_path, mode="ppo", updates=1)
    assert not trainer.net.has_heads
    metrics = trainer.train()
    assert metrics["charts/intrinsic_reward_a"] == 0 and metrics["charts/intrinsic_reward_hc"] == 0
    assert metrics["charts/target_coverage"] == 0 and metrics["charts/cache_hit_rate"] == 0
    assert metrics["losses/value_loss_int"] == 0
    assert not any(k.startswith("losses/distill") for k in metrics)


def test_noreward_mode_trains_heads_without_paying(tmp_path):
    trainer, _ = make_trainer(tmp_path, mode="illm-noreward", updates=1)
    head_before = trainer.net.f_a[0].weight.detach().clone()
    metrics = trainer.train()
    assert metrics["losses/distill_action"] > 0 and metrics["losses/value_loss_int"] == 0
    assert "charts/intrinsic_reward" not in metrics and metrics["charts/intrinsic_reward_a"] > 0
    assert not torch.equal(head_before, trainer.net.f_a[0].weight)


def test_records_carry_the_rolling_history(tmp_path):
    trainer, provider = make_trainer(tmp_path, updates=1, history_len=2)
    trainer.train()
    assert len(provider.records) == 4 * 32 and provider.calls == 1
    assert all(len(r.history) <= 2 and r.valid_actions == ACTIONS for r in provider.records)
    assert any(len(r.history) == 2 for r in provider.records)
    assert all(r.history == () for r in provider.records if r.observation.startswith("you see a wall 0 "))


def test_short_run_writes_metrics_and_checkpoint_and_resumes(tmp_path):
    trainer, _ = make_trainer(tmp_path, updates=2, checkpoint_every=1)
    seen = []
    trainer.on_metrics = seen.append
    trainer.train()
    run = tmp_path / "run"
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["global_step"] for r in rows] == [128, 256] and len(seen) == 2
    for key in ("charts/sps", "charts/intrinsic_reward_a", "charts/intrinsic_reward_hc", "charts/cache_hit_rate",
                "charts/target_coverage", "charts/live_annotations", "losses/policy_loss",
                "losses/value_loss", "losses/entropy", "losses/distill_action", "losses/distill_summary"):
        assert key in rows[-1], key
    assert rows[-1]["charts/cache_hit_rate"] == 0.25 and rows[-1]["charts/live_annotations"] == 7
    assert 0 < rows[-1]["charts/target_coverage"] < 1
    saved = load_checkpoint(run)
    assert saved["global_step"] == 256 and saved["update"] == 2

    with pytest.raises(OutputExistsError):
        make_trainer(tmp_path, updates=3)
    with pytest.raises(UsageError, match="lambda_a"):
        make_trainer(tmp_path, updates=3, resume=True, lambda_a=0.1)

    resumed, _ = make_trainer(tmp_path, updates=3, resume=True, checkpoint_every=1)
    assert resumed.global_step == 256 and resumed.update_idx == 2
    state, before = resumed.state_dict(), trainer.state_dict()
    for k in before["model"]:
        assert torch.equal(state["model"][k], before["model"][k]), k
    assert torch.equal(state["rng"]["torch"], before["rng"]["torch"])
    assert state["rng"]["numpy"] == before["rng"]["numpy"] and state["bonus"] == before["bonus"]
    opt_a, opt_b = state["optimizer"]["state"], before["optimizer"]["state"]
    assert all(torch.equal(opt_a[i]["exp_avg"], opt_b[i]["exp_avg"]) for i in opt_b)
    resumed.train()
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in rows] == [1, 2, 3] and load_checkpoint(run)["global_step"] == 384


def test_training_freezes_what_the_run_was_built_with_and_puts_it_back(tmp_path, monkeypatch):
    """While a run trains, the objects it was built with are out of the collector's passes and its
    young generation is larger (`frozen_heap`); after it (or a failure) both are back; a process's
    own freeze, and its thresholds, are left alone: none of the collector's settings is touched (a
    frozen object still dies when its last reference goes, on pytest-xdist's thread too, so the
    frozen count may fall meanwhile: it failed a fast-tier run at 784,195 against 784,197)."""
    import gc

    from illm_tools.rl.threads import YOUNG_THRESHOLD, frozen_heap

    trainer, _ = make_trainer(tmp_path, updates=2)
    during = []
    trainer.on_metrics = lambda m: during.append((gc.get_freeze_count(), gc.get_threshold()))
    assert gc.get_freeze_count() == 0
    before = gc.get_threshold()
    trainer.train()
    assert len(during) == 2 and min(count for count, _ in during) > 0 and gc.get_freeze_count() == 0
    assert all(t == (YOUNG_THRESHOLD, *before[1:]) for _, t in during) and gc.get_threshold() == before
    with pytest.raises(RuntimeError), frozen_heap():
        raise RuntimeError
    assert gc.get_freeze_count() == 0 and gc.get_threshold() == before
    gc.freeze()
    try:
        host, touched = gc.get_freeze_count(), []
        with monkeypatch.context() as spied:
            for name in ("freeze", "unfreeze", "set_threshold"):
                spied.setattr(gc, name, lambda *a, name=name: touched.append(name))
            with frozen_heap():
                assert 0 < gc.get_freeze_count() <= host and gc.get_threshold() == before
        assert not touched and 0 < gc.get_freeze_count() <= host and gc.get_threshold() == before
    finally:
        gc.unfreeze()


def test_config_is_validated():
    with pytest.raises(UsageError, match="unknown method 'curiosity'"):
        TrainConfig(method="curiosity")
    with pytest.raises(UsageError, match="divisible"):
        TrainConfig.from_dict(dict(num_envs=3, num_steps=5, num_minibatches=4))
    cfg = TrainConfig(num_envs=16, num_steps=128, total_steps=10_000)
    assert (cfg.batch_size, cfg.minibatch_size, cfg.num_updates) == (2048, 512, 4)
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg


def test_illm_mode_needs_a_provider(tmp_path):
    cfg = TrainConfig(run_dir=tmp_path, num_envs=4, num_steps=32)
    with pytest.raises(UsageError, match="ppo"):
        Trainer(cfg.resolved(), FakePool(4), None)


def test_real_babyai_pool_short_run_and_load_policy(tmp_path):
    cfg = TrainConfig.from_dict(dict(env_id="BabyAI-GoToRedBallGrey-v0", run_dir=tmp_path / "run", num_envs=4, num_steps=32,
                      total_steps=128, llm=LLMSpec("stub", "stub:8"), head_hidden=32, tensorboard=False))
    pool = make_pool(cfg)
    provider = FakeProvider(len(pool.action_names), cfg.embedding_dim)
    metrics = Trainer(cfg.resolved(), pool, provider).train()
    assert metrics["global_step"] == 128 and np.isfinite(metrics["losses/policy_loss"])
    assert all(r.observation for r in provider.records) and provider.records[0].mission.startswith("go to")
    policy = load_policy(cfg.run_dir, pool, seed=0)
    actions = policy.act(pool.reset())
    assert actions.shape == (4,) and ((0 <= actions) & (actions < len(pool.action_names))).all()


def test_choosing_the_heads_dtype_leaves_the_seeded_rng_alone():
    """The bf16-or-float32 timing runs inside the seeded network init: it must draw no numbers."""
    from illm_tools.llm import dtype
    from illm_tools.rl.networks import bf16_is_faster

    dtype._measured.cache_clear()
    before = torch.random.get_rng_state()
    assert isinstance(bf16_is_faster(), bool)
    assert torch.equal(before, torch.random.get_rng_state())
