"""The docs' bonus example (docs/examples/count_bonus.py) is a template a built-in would pass for: registered
as docs/extending/bonus.md says a user does (one file, one registry entry), it gets the checks
tests/test_methods.py gives every built-in method (its reward reaches the advantages the loss uses;
it trains end to end through `illm train` and `illm eval`), and it pays as the built-ins pay:
normalised (so its own units do not matter), nothing where the method does not pay, its normaliser
checkpointed."""

from __future__ import annotations

import importlib

import pytest
import torch

from illm_tools.intrinsic import BonusContext
from illm_tools.intrinsic.registry import METHODS, Method, register
from fakes import EXAMPLES, bonus_reaches_the_advantages, trains_end_to_end

pytestmark = pytest.mark.usefixtures("one_torch_thread")

OWN = ("exponent=1.0", "charts/count_distinct", "reward_norm")  # test_methods.OWN's entry for it


@pytest.fixture
def example(monkeypatch):
    """The example's module, its `METHOD` registered (the one registry entry of bonus.md)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    module = importlib.import_module("count_bonus")
    register(module.METHOD)
    try:
        yield module
    finally:
        METHODS.pop(module.METHOD.name)


def test_the_example_bonus_reaches_the_advantages_the_loss_uses(example, tmp_path, monkeypatch):
    bonus_reaches_the_advantages(tmp_path, monkeypatch, example.METHOD.name, OWN[1])


def test_the_example_method_trains_end_to_end(example, tmp_path):
    trains_end_to_end(tmp_path, example.METHOD.name, *OWN)


def rollouts(seed: int, steps: int = 3) -> list[torch.Tensor]:
    """Rollouts [T=8, N=4] of 7x7x3 grids drawn from a few distinct ones (so counts grow)."""
    gen = torch.Generator().manual_seed(seed)
    grids = torch.randint(0, 6, (5, 7, 7, 3), generator=gen, dtype=torch.uint8)
    return [grids[torch.randint(0, 5, (8, 4), generator=gen)] for _ in range(steps)]


def paid(bonus, images: torch.Tensor):
    for step in images:
        bonus.observe({"next_images": step})
    return bonus.compute_rewards({"next_images": images})


def test_it_pays_normalised_only_when_paid_and_keeps_its_scale_across_a_resume(example):
    ctx = BonusContext(num_envs=4, num_steps=8, image_shape=(7, 7, 3), num_actions=6, feature_dim=8, int_gamma=0.99,
                       seed=0)
    method = example.METHOD
    small, large = (method.build({}, {"scale": s}, ctx) for s in (1.0, 100.0))
    for images in rollouts(0):
        a, b = paid(small, images), paid(large, images)
        # the normaliser divides the bonus's units out, and what it paid is logged
        assert torch.allclose(a.reward, b.reward, rtol=1e-4) and a.reward.abs().max() < 10
        assert a.logs["intrinsic_reward"] == pytest.approx(float(a.reward.mean()), rel=1e-5)
        assert b.logs["count_raw"] == pytest.approx(100 * a.logs["count_raw"], rel=1e-5)

    unpaid = Method("count-unpaid", "counted, not paid", example.CountBonus, pays_reward=False).build({}, {}, ctx)
    for images in rollouts(0):
        out = paid(unpaid, images)
        assert torch.equal(out.reward, torch.zeros(8, 4)) and "intrinsic_reward" not in out.logs
    assert out.logs["count_distinct"] == 5  # it still counts

    resumed = method.build({}, {}, ctx)
    resumed.load_state_dict(small.state_dict())
    assert resumed.reward_norm.rms.var == small.reward_norm.rms.var
