"""How the bonus enters the advantages (issue 28's knobs): the paper's one reward stream with one
critic, the intrinsic weight's schedule (annealed, success-gated), the cap that holds the bonus to
a multiple of the task's advantage, and what a run logs about them (the bonus's weight, the
heads' agreement with the annotator, where the bonus was paid). Each on a tiny run: the bonus
reaches the advantages as specified and a resumed run goes on with the knob's state."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from illm_tools.errors import UsageError
from illm_tools.rl import Rollout, TrainConfig, Trainer, gae, load_checkpoint, two_stream_advantages
from illm_tools.rl.bonus_schedule import BonusSchedule
from illm_tools.rl.storage import capped

from fakes import FakePool, FakeProvider, make_trainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _rollout(seed=0, t=6, n=3):
    g = torch.Generator().manual_seed(seed)
    ro = Rollout.empty(t, n, (7, 7, 3), 4)
    ro.rewards[:] = (torch.rand(t, n, generator=g) > 0.8).float()
    ro.ends[:] = (torch.rand(t, n, generator=g) > 0.7).float()
    ro.values_ext[:] = torch.rand(t, n, generator=g)
    ro.values_int[:] = torch.rand(t, n, generator=g)
    bonus = torch.rand(t, n, generator=g)
    return ro, bonus, torch.rand(n, generator=g), torch.rand(n, generator=g)


KW = dict(gamma=0.99, int_gamma=0.9, lam=0.95, int_episodic=False)


def test_one_stream_is_gae_of_the_summed_reward_with_one_critic():
    ro, bonus, next_ext, next_int = _rollout()
    adv = two_stream_advantages(ro, bonus, next_ext, next_int, ext_coef=1.0, int_coef=0.5, streams=1, **KW)
    expected, ret = gae(ro.rewards + 0.5 * bonus, ro.values_ext, next_ext, ro.ends, 0.99, 0.95)
    assert torch.allclose(adv.advantages, expected) and torch.allclose(adv.returns_ext, ret)
    assert not adv.int_stream and adv.returns_int.abs().sum() == 0  # the intrinsic head learns nothing
    # the parts: GAE is linear in the reward, so the bonus's part is its episodic (gamma lambda)-discounted sum
    ext_only, _ = gae(ro.rewards, ro.values_ext, next_ext, ro.ends, 0.99, 0.95)
    assert torch.allclose(adv.ext_part, ext_only, atol=1e-6)
    assert torch.allclose(adv.ext_part + adv.int_part, adv.advantages)
    running = torch.zeros(3)
    for t in reversed(range(6)):  # cut at episode ends, as r* is episodic
        running = 0.5 * bonus[t] + 0.99 * 0.95 * (1 - ro.ends[t]) * running
        assert torch.allclose(adv.int_part[t], running, atol=1e-6)
    two = two_stream_advantages(ro, bonus, next_ext, next_int, ext_coef=1.0, int_coef=0.5, **KW)
    assert two.int_stream and not torch.allclose(two.advantages, adv.advantages)


def test_the_cap_holds_the_bonus_to_a_multiple_of_the_task_advantage_where_the_task_pays():
    ext, intr = torch.tensor([1.0, -1.0, 0.0]), torch.tensor([4.0, 4.0, -4.0])
    scaled, factor = capped(ext, intr, 0.5)  # mean |ext| 2/3, mean |int| 4: scaled to 1/3
    assert factor == pytest.approx(1 / 12) and scaled.abs().mean().item() == pytest.approx(0.5 * 2 / 3)
    out, factor = capped(torch.zeros(3), intr, 0.5)  # nothing found yet: the bonus steers alone
    assert out is intr and factor == 1.0
    small = intr * 0.01  # already under the cap: as it is
    out, factor = capped(ext, small, 0.5)
    assert out is small and factor == 1.0
    assert capped(ext, intr, 0.0)[1] == 1.0  # 0: no cap
    ro, bonus, next_ext, next_int = _rollout()
    adv = two_stream_advantages(ro, bonus * 100, next_ext, next_int, ext_coef=1.0, int_coef=1.0, int_ext_cap=0.5, **KW)
    assert adv.int_scale < 1 and adv.int_part.abs().mean().item() == pytest.approx(0.5 * adv.ext_part.abs().mean().item(), rel=1e-5)


def test_the_cap_keeps_the_bonus_from_taking_over_as_the_task_s_advantage_fades():
    """Issue 71's failed seed: the task's reward was found, then its advantage faded (the critic had
    learned it, the policy drifted) while the bonus's did not, and |A_int|/|A_ext| climbed from ~1 to
    ~6 as the seed forgot the task. A fake run of rollouts whose rewards fade the same way: uncapped,
    the ratio climbs; with int_ext_cap 1 it stays at most 1 in every rollout where the task still
    pays, so the task keeps at least half of the advantage's steer."""
    ratios = {0.0: [], 1.0: []}
    for fade in (1.0, 0.3, 0.1, 0.03, 0.01):
        ro, bonus, next_ext, next_int = _rollout(seed=1, t=32, n=4)
        ro.rewards *= fade  # the task pays less and less of what it paid
        ro.values_ext *= fade  # the critic follows it
        next_ext = next_ext * fade
        for cap in ratios:
            adv = two_stream_advantages(ro, bonus, next_ext, next_int, ext_coef=1.0, int_coef=1.0, int_ext_cap=cap, **KW)
            ratios[cap].append(adv.scale_logs()["adv_int_ext_ratio"])
            if cap:
                assert adv.int_part.abs().mean() <= cap * adv.ext_part.abs().mean() * (1 + 1e-5)
    uncapped, capped_run = ratios[0.0], ratios[1.0]
    assert all(b > a for a, b in zip(uncapped, uncapped[1:])) and uncapped[-1] > 50 * uncapped[0]
    assert max(capped_run) <= 1.0 + 1e-5 and capped_run[-1] == pytest.approx(1.0, rel=1e-4)


def test_the_schedules_weights():
    anneal = BonusSchedule("anneal", 4)
    assert [anneal.weight(u) for u in (1, 2, 3, 4)] == [1.0, 0.75, 0.5, 0.25]
    gate = BonusSchedule("success", 10)
    assert gate.weight(1) == 1.0
    gate.observe(float("nan"))  # no episode ended: nothing learned
    gate.observe(None)
    assert gate.weight(2) == 1.0
    for _ in range(50):
        gate.observe(1.0)
    assert gate.weight(3) < 0.01
    with pytest.raises(ValueError):
        BonusSchedule("cosine", 3)


def _capture(trainer, monkeypatch):
    seen = {}
    real_update = trainer.update

    def capture(ro, adv):
        seen.update(ro=ro, adv=adv, weight=trainer.bonus_weight())  # the weight these advantages were made with
        with torch.no_grad():
            seen["next"] = trainer.net(*trainer._policy_inputs(trainer.obs))
        return real_update(ro, adv)

    monkeypatch.setattr(trainer, "update", capture)
    return seen


@pytest.mark.parametrize("knobs", [dict(reward_streams=1), dict(bonus_schedule="anneal"),
                                   dict(bonus_schedule="success"), dict(int_ext_cap=0.25)])
def test_each_knob_reaches_the_advantages_the_loss_uses_and_resumes(tmp_path, monkeypatch, knobs):
    trainer, _ = make_trainer(tmp_path, updates=3, checkpoint_every=1, **knobs)
    seen = _capture(trainer, monkeypatch)
    bonuses = []
    real_rewards = trainer.intrinsic_rewards
    monkeypatch.setattr(trainer, "intrinsic_rewards", lambda ro, batch=None: bonuses.append(real_rewards(ro, batch))
                        or bonuses[-1])
    trainer.train_one_update()
    trainer.train_one_update()  # the second update: the schedule has moved
    cfg, ro, adv, nxt = trainer.cfg, seen["ro"], seen["adv"], seen["next"]
    weight = seen["weight"]
    expected = two_stream_advantages(ro, bonuses[-1].reward, nxt.value_ext, nxt.value_int, gamma=cfg.ppo.gamma,
                                     int_gamma=cfg.bonus.int_gamma, lam=cfg.ppo.gae_lambda, ext_coef=cfg.bonus.ext_coef,
                                     int_coef=cfg.bonus.int_coef * weight, int_episodic=cfg.bonus.int_episodic,
                                     streams=cfg.bonus.reward_streams, int_ext_cap=cfg.bonus.int_ext_cap)
    assert torch.allclose(adv.advantages, expected.advantages, atol=1e-5)  # the loss saw the bonus as specified
    if knobs.get("bonus_schedule") == "anneal":
        assert weight == pytest.approx(1 - 1 / 3)
    if knobs.get("bonus_schedule") == "success":  # the first update's episodes set the second's weight
        assert 0 < trainer.schedule.success < 1 and weight < 1
    if knobs.get("reward_streams") == 1:
        assert not adv.int_stream
    trainer.save()
    state = load_checkpoint(cfg.run_dir)
    assert state["bonus_schedule"]["success"] == trainer.schedule.success
    resumed = Trainer(TrainConfig.from_dict(dict(**{**cfg.to_dict(), "resume": True})).resolved(), FakePool(cfg.num_envs),
                      FakeProvider(6, cfg.embedding_dim))
    assert resumed.update_idx == 2 and resumed.schedule.success == trainer.schedule.success
    assert resumed.bonus_weight() == trainer.bonus_weight()
    third = resumed.schedule.weight(3)  # from the restored state: anneal 1/3, success 1 - its rate, else 1
    assert resumed.train()["charts/bonus_weight"] == pytest.approx(third)
    if knobs.get("bonus_schedule") == "anneal":
        assert third == pytest.approx(1 / 3)


def test_one_stream_trains_no_intrinsic_value_head(tmp_path):
    trainer, _ = make_trainer(tmp_path, updates=1, reward_streams=1)
    head = trainer.net.value_int.weight.detach().clone() if hasattr(trainer.net, "value_int") else None
    metrics = trainer.train()
    assert metrics["losses/value_loss_int"] == 0 and metrics["charts/adv_int_abs"] > 0
    if head is not None:
        assert torch.equal(head, trainer.net.value_int.weight)


def test_a_run_logs_the_heads_agreement_the_weight_and_where_the_bonus_was_paid(tmp_path):
    from illm_tools.rl.visitation import BONUS_FILE, FILE

    trainer, _ = make_trainer(tmp_path, updates=2, pool=FakePool(4, positions=True))
    metrics = trainer.train()
    assert 0 <= metrics["charts/head_agreement"] <= 1 and metrics["charts/bonus_weight"] == 1.0
    visits, paid = np.load(tmp_path / "run" / FILE), np.load(tmp_path / "run" / BONUS_FILE)
    assert paid.dtype == np.float64 and paid.sum() > 0
    assert (paid[visits == 0] == 0).all()  # paid only where the agent was
    assert set(np.flatnonzero(paid.sum(1))) <= set(range(4))  # env i stands on row i


def test_bad_knobs_are_refused_in_one_line(tmp_path):
    with pytest.raises(UsageError, match="reward-streams"):
        TrainConfig.from_dict(dict(run_dir=tmp_path / "r", method="ppo", reward_streams=3))
    with pytest.raises(UsageError, match="bonus-schedule"):
        TrainConfig.from_dict(dict(run_dir=tmp_path / "r", method="ppo", bonus_schedule="cosine"))
    with pytest.raises(UsageError, match="success rate"):
        TrainConfig.from_dict(dict(run_dir=tmp_path / "r", method="rnd", env_id="ALE/Pong-v5", bonus_schedule="success"))
    with pytest.raises(UsageError, match="int_ext_cap|int-ext-cap"):
        TrainConfig.from_dict(dict(run_dir=tmp_path / "r", method="ppo", int_ext_cap=-1))
