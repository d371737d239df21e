"""The bonus plug-in contract: methods come from the registry, bonus options are typed and checked,
the rollout hands every bonus its next observations, and a bonus defined here (a count-based toy)
trains through the unchanged Trainer with its rewards reaching the advantages."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import pytest
import torch
from typer.testing import CliRunner

from cli.main import app
from illm_tools.errors import UsageError
from illm_tools.intrinsic import BonusRewards, IntrinsicBonus, NoBonus
from illm_tools.intrinsic.registry import METHODS, Method, get_method, register
from illm_tools.rl import TrainConfig, load_checkpoint

from illm_tools.rl.networks import GRID_CHANNEL_SIZES, GridMissionNet
from fakes import make_trainer, one_update_seen

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# --- a bonus the trainer has never heard of ---------------------------------------------------
@dataclass
class CountConfig:
    """The toy's settings."""

    scale: float = 1.0
    """Reward of a never-seen observation."""


class CountBonus(IntrinsicBonus):
    """Pays scale / sqrt(n) for reaching an observation seen n times (counted in `observe`)."""

    config_class = CountConfig

    def __init__(self, config: CountConfig, ctx):
        self.scale, self.ctx = config.scale, ctx
        self.counts: Counter[bytes] = Counter()
        self.observed = self.updates = 0
        self.last_reward: torch.Tensor | None = None

    def observe(self, step):
        n = self.ctx.num_envs
        assert step["images"].shape == step["next_images"].shape == (n, *self.ctx.image_shape)
        assert step["actions"].shape == step["ends"].shape == (n,)
        assert step["features"].shape == (n, self.ctx.feature_dim)
        self.observed += 1
        for image in step["next_images"]:
            self.counts[image.numpy().tobytes()] += 1

    def compute_rewards(self, batch):
        images = batch["next_images"]
        t, n = images.shape[:2]
        assert "target_mask" not in batch and "action_logits" not in batch  # declared neither
        counts = torch.tensor([self.counts[x.numpy().tobytes()] for x in images.reshape(t * n, -1)],
                              dtype=torch.float32)
        self.last_reward = self.scale / counts.clamp_min(1.0).sqrt().view(t, n)
        return BonusRewards(self.last_reward, {"count_unique": float(len(self.counts))})

    def update(self, batch):
        self.updates += 1
        return {"count_updates": float(self.updates)}

    def state_dict(self):
        return {"observed": self.observed, "updates": self.updates, "unique": len(self.counts)}

    def load_state_dict(self, state):
        self.observed, self.updates = state["observed"], state["updates"]


@pytest.fixture
def count_method():
    method = register(Method("count-toy", "a count-based toy", CountBonus))
    yield method
    METHODS.pop(method.name)


# --- the registry -----------------------------------------------------------------------------
def test_methods_and_what_each_declares():
    assert list(METHODS)[:4] == ["illm", "illm-noreward", "ppo", "rnd"]
    illm, noreward, ppo, rnd = (get_method(m) for m in ("illm", "illm-noreward", "ppo", "rnd"))
    assert illm.needs_targets and illm.policy_heads and illm.pays
    assert noreward.needs_targets and noreward.policy_heads and not noreward.pays
    assert ppo.bonus_class is NoBonus and not (ppo.needs_targets or ppo.policy_heads or ppo.pays)
    assert not (rnd.needs_targets or rnd.policy_heads) and rnd.pays and rnd.preset == "rnd"
    assert TrainConfig(method="rnd").uses_heads is False and TrainConfig(method="rnd").pays_bonus


def test_an_unknown_method_is_refused_in_one_line(tmp_path):
    with pytest.raises(UsageError, match="unknown method") as err:
        TrainConfig(method="curiosity")
    assert "\n" not in str(err.value) and "rnd" in str(err.value)
    result = CliRunner().invoke(app, ["train", "--method", "curiosity", "--out", str(tmp_path / "r")])
    assert result.exit_code == 1 and "unknown method" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_method_help_lists_the_registry(count_method):
    from illm_tools.intrinsic.registry import method_help

    assert all(name in method_help() for name in ("illm-noreward", "ppo", "rnd", "count-toy"))
    with pytest.raises(UsageError, match="already registered"):
        register(Method("rnd", "again", CountBonus))


def test_bonus_options_are_typed_and_checked():
    rnd = get_method("rnd")
    assert rnd.parse_options(["update_proportion=0.5", "epochs = 2"]) == {"update_proportion": 0.5, "epochs": 2}
    cfg = TrainConfig(method="rnd", bonus_options={"update_proportion": 1})
    assert rnd.make_config(cfg.to_dict(), cfg.bonus_options).update_proportion == 1.0
    for bad, match in ((["epochs=two"], "epochs must be int"), (["bogus=1"], "no bonus option bogus"),
                       (["update_proportion"], "KEY=VALUE"), (["update_proportion=1.5"], r"\(0, 1\]")):
        with pytest.raises(UsageError, match=match):
            TrainConfig(method="rnd", bonus_options=rnd.parse_options(bad))
    # iLLM's settings are the run's own (top-level options), not bonus options; ppo has none
    with pytest.raises(UsageError, match="it takes none"):
        TrainConfig(method="illm", bonus_options={"lambda_a": 0.1})
    with pytest.raises(UsageError, match="ppo has no bonus option"):
        TrainConfig(method="ppo", bonus_options={"scale": 1})
    illm = get_method("illm").make_config(TrainConfig.from_dict({"lambda_a": 0.3}).to_dict(), {})
    assert illm.lambda_a == 0.3 and illm.beta_hc == 0.05  # the small preset's, TrainConfig's default


# --- the trainer side -------------------------------------------------------------------------
def test_the_rollout_hands_bonuses_the_next_observations(tmp_path):
    trainer, _ = make_trainer(tmp_path, "ppo", updates=1)
    ro, _, _, _ = trainer.collect_rollout()
    assert torch.equal(ro.next_images[:-1], ro.images[1:]) and torch.equal(ro.next_missions[:-1], ro.missions[1:])
    last_images, last_missions = trainer._policy_inputs(trainer.obs)  # where the next rollout starts
    assert torch.equal(ro.next_images[-1], last_images) and torch.equal(ro.next_missions[-1], last_missions)
    assert ro.ends.sum() > 0  # episodes ended in the rollout: their next observation is the reset one
    # stored once: the next observations are a view of the same T + 1 observations, not a copy
    assert ro.next_images.untyped_storage().data_ptr() == ro.images.untyped_storage().data_ptr()
    assert ro.observations.shape[0] == ro.num_steps + 1
    batch = trainer.bonus_batch(ro)
    assert set(batch) == {"images", "missions", "actions", "ends", "next_images", "next_missions", "features"}
    assert batch["features"].shape == (32, 4, trainer.net.feature_dim) and batch["features"].abs().sum() > 0


def test_a_bonus_defined_outside_plugs_in_and_reaches_the_advantages(tmp_path, monkeypatch, count_method):
    trainer, _ = make_trainer(tmp_path, "count-toy", updates=3, checkpoint_every=1, bonus_options={"scale": 2.0})
    bonus = trainer.bonus
    assert isinstance(bonus, CountBonus) and bonus.scale == 2.0 and not trainer.net.has_heads
    assert trainer.provider is None and trainer.cfg.pays_bonus

    seen = one_update_seen(trainer, monkeypatch)
    cfg, adv, metrics = trainer.cfg, seen.adv, seen.logged
    assert bonus.observed == cfg.num_steps and bonus.updates == 1
    assert (bonus.last_reward > 0).all() and (bonus.last_reward <= 2.0).all()
    assert torch.equal(seen.bonus, bonus.last_reward)
    assert torch.allclose(adv.advantages, seen.expected.advantages, atol=1e-6)  # the loss saw the bonus ...
    assert (adv.advantages - seen.without.advantages).abs().max() > 0.1      # ... and it changed them
    assert metrics["charts/count_unique"] > 0 and metrics["losses/count_updates"] == 1
    assert metrics["charts/adv_int_abs"] > 0 and metrics["losses/value_loss_int"] > 0

    monkeypatch.undo()
    trainer.train()
    assert bonus.updates == 3 and bonus.observed == 3 * cfg.num_steps
    assert load_checkpoint(cfg.run_dir)["bonus"] == bonus.state_dict()
    resumed, _ = make_trainer(tmp_path, "count-toy", updates=4, resume=True, bonus_options={"scale": 2.0})
    assert resumed.bonus.updates == 3 and resumed.bonus.observed == 3 * cfg.num_steps
    with pytest.raises(UsageError, match="bonus_options"):
        make_trainer(tmp_path, "count-toy", updates=4, resume=True, bonus_options={"scale": 3.0})


# --- a policy network plugged in from this file ------------------------------------------------
@dataclass
class TinyOptions:
    width: int = 8


class TinyNet(GridMissionNet):
    """A torso of one linear layer over the flattened one-hot grid and the mission encoder."""

    Options = TinyOptions

    def build_torso(self, *, vocab_size, image_shape, options=None, **_):
        options = options or TinyOptions()
        cells = image_shape[0] * image_shape[1] * sum(GRID_CHANNEL_SIZES)
        self.flat = torch.nn.Linear(cells, options.width)
        return options.width + self.build_mission_encoder(vocab_size, 4, 4)

    def features(self, images, missions):
        return torch.cat([self.flat(self.one_hot_grid(images).flatten(1)), self.encode_mission(missions)], dim=1)


def test_a_network_registered_from_a_test_file_trains_without_trainer_changes(tmp_path):
    method = register(Method("tiny-net", "a tiny torso", None, pays_reward=False, network=TinyNet))
    try:
        trainer, _ = make_trainer(tmp_path, "tiny-net", network_options={"width": "6"})
        assert isinstance(trainer.net, TinyNet) and trainer.net.feature_dim == 6 + 4
        trainer.train()
        state = load_checkpoint(tmp_path / "run")["model"]
        assert state["flat.weight"].shape[0] == 6 and not any(k.startswith("image_conv") for k in state)
        with pytest.raises(UsageError, match="no network option depth"):
            TrainConfig(method=method.name, network_options={"depth": 2})
    finally:
        METHODS.pop(method.name)
