"""RND: a frozen target, a predictor that learns what it sees (so the reward for a repeated
observation falls), observation normalisation, checkpoint resume (`illm train --method rnd` end to
end: tests/test_methods.py)."""

from __future__ import annotations

import pytest
import torch

from illm_tools.intrinsic import BonusContext, RNDBonus, RNDConfig
from illm_tools.rl import Trainer, load_checkpoint
from illm_tools.rl.build import run_config
from fakes import FakePool

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CTX = BonusContext(num_envs=4, num_steps=16, image_shape=(7, 7, 3), num_actions=3, feature_dim=8,
                   int_gamma=0.99, seed=0)


def images(count: int, seed: int) -> torch.Tensor:
    """`count` random MiniGrid-like views (object, colour, state codes)."""
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 6, (count, 7, 7, 3), generator=g, dtype=torch.uint8)


def repeated_rollout(seen: torch.Tensor) -> dict:
    """A [16, 4] rollout whose next observations cycle through `seen`."""
    return {"next_images": seen[torch.arange(64) % len(seen)].view(16, 4, 7, 7, 3)}


def test_the_predictor_learns_repeated_observations_and_their_reward_falls():
    torch.manual_seed(0)
    bonus = RNDBonus(RNDConfig(), CTX)
    target_before = {k: v.clone() for k, v in bonus.target.state_dict().items()}
    predictor_before = {k: v.clone() for k, v in bonus.predictor.state_dict().items()}
    seen = images(4, seed=1)
    batch = repeated_rollout(seen)
    errors, rewards, losses = [], [], []
    for _ in range(6):
        out = bonus.compute_rewards(batch)
        errors.append(out.logs["rnd_error"])
        rewards.append(float(out.reward.mean()))
        losses.append(bonus.update(batch)["rnd_predictor_loss"])
        assert out.reward.shape == (16, 4) and (out.reward > 0).all()
    assert losses[-1] < 0.5 * losses[0]
    assert errors == sorted(errors, reverse=True) and errors[-1] < 0.5 * errors[0]
    assert rewards == sorted(rewards, reverse=True) and rewards[-1] < 0.5 * rewards[0]
    # what it has seen is now less novel than what it has not
    novel_error = bonus.prediction_error(bonus.normalise(images(4, seed=2))).mean()
    assert bonus.prediction_error(bonus.normalise(seen)).mean() < 0.5 * novel_error
    # the target never moved and is not trained; the predictor did
    assert all(torch.equal(v, target_before[k]) for k, v in bonus.target.state_dict().items())
    assert not any(p.requires_grad for p in bonus.target.parameters())
    trained = {id(p) for group in bonus.optimizer.param_groups for p in group["params"]}
    assert trained == {id(p) for p in bonus.predictor.parameters()}
    assert not all(torch.equal(v, predictor_before[k]) for k, v in bonus.predictor.state_dict().items())


def test_observations_are_normalised_from_the_first_rollout_then_merged_after_rewarding():
    bonus = RNDBonus(RNDConfig(obs_clip=2.0), CTX)
    first, second = repeated_rollout(images(8, seed=3)), repeated_rollout(images(8, seed=4))
    bonus.compute_rewards(first)  # statistics start from the first rollout's observations
    x = first["next_images"].reshape(-1, 7, 7, 3).double()
    assert bonus.obs_rms.count == pytest.approx(64, abs=1e-3)
    assert torch.allclose(torch.as_tensor(bonus.obs_rms.mean), x.mean(0), atol=1e-4)
    normalised = bonus.normalise(first["next_images"])
    assert normalised.shape == (64, 147) and normalised.abs().max() <= 2.0
    mean_before = bonus.obs_rms.mean.copy()
    error = bonus.prediction_error(bonus.normalise(second["next_images"]))  # with the statistics as they were
    out = bonus.compute_rewards(second)
    assert torch.allclose(torch.tensor(out.logs["rnd_error"]), error.mean())
    assert bonus.obs_rms.count == pytest.approx(128, abs=1e-3) and not (bonus.obs_rms.mean == mean_before).all()


def rnd_trainer(tmp_path, updates, **kw):
    cfg = run_config(dict(run_dir=tmp_path / "run", method="rnd", num_envs=4, num_steps=32,  # rnd's preset, as the CLI
                          total_steps=4 * 32 * updates, tensorboard=False, update_epochs=2, num_minibatches=2, **kw))
    return Trainer(cfg.resolved(), FakePool(cfg.num_envs))


def test_rnd_trains_through_the_trainer_and_its_state_survives_a_resume(tmp_path):
    trainer = rnd_trainer(tmp_path, updates=2, checkpoint_every=1)
    assert isinstance(trainer.bonus, RNDBonus) and not trainer.net.has_heads and trainer.provider is None
    assert (trainer.cfg.bonus.ext_coef, trainer.cfg.bonus.int_coef) == (2.0, 1.0)
    metrics = trainer.train()
    for key in ("charts/intrinsic_reward", "charts/rnd_error", "losses/rnd_predictor_loss", "charts/adv_int_abs",
                "losses/value_loss_int"):
        assert metrics[key] > 0, key
    assert not any(k.startswith("losses/distill") for k in metrics)
    saved = load_checkpoint(trainer.cfg.run_dir)["bonus"]

    resumed = rnd_trainer(tmp_path, updates=3, resume=True, checkpoint_every=1)
    state, before = resumed.bonus.state_dict(), trainer.bonus.state_dict()
    for part in ("target", "predictor"):
        assert all(torch.equal(state[part][k], before[part][k]) for k in before[part]), part
    assert state["obs_rms"] == before["obs_rms"] == saved["obs_rms"] and state["reward_norm"] == before["reward_norm"]
    assert torch.equal(state["generator"], before["generator"])
    opt_a, opt_b = state["optimizer"]["state"], before["optimizer"]["state"]
    assert opt_b and all(torch.equal(opt_a[i]["exp_avg"], opt_b[i]["exp_avg"]) for i in opt_b)
    target = {k: v.clone() for k, v in resumed.bonus.target.state_dict().items()}
    resumed.train()
    assert load_checkpoint(trainer.cfg.run_dir)["global_step"] == 384
    assert all(torch.equal(v, target[k]) for k, v in resumed.bonus.target.state_dict().items())


