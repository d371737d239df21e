"""Fidelity to the paper and to RND: f^a's argmax target (Alg. 1 line 7), the GoTo levels' default
action space (Tables 1 and 5) recorded resolved by collect and train, and the bonus's scale
next to the task reward (charts/adv_int_ext_ratio) with the --bonus-preset weights."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from illm_tools.collect import CollectConfig, collect
from illm_tools.errors import UsageError
from illm_tools.rl import Rollout, TrainConfig, load_checkpoint, two_stream_advantages
from illm_tools.intrinsic.presets import bonus_weights
from illm_tools.rl.targets import CachedTargets
from illm_tools.tasks.calibration import action_distribution, action_target
from illm_tools.tasks.state import StateRecord

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ENV = "BabyAI-GoToLocal-v0"


# --- A. f^a's target -------------------------------------------------------------------------
SUMS = np.array([[-3.0, -1.0, -2.0], [-4.0, -6.0, -5.0]])
COUNTS = np.array([[1, 3, 1], [2, 1, 1]])
NEUTRAL = np.array([[-5.0, -0.5, -4.0], [-1.0, -6.0, -6.0]])


@pytest.mark.parametrize("calibration,best", [("sum", [1, 0]), ("mean", [1, 0]), ("pmi", [0, 2])])
def test_argmax_target_is_the_one_hot_of_the_best_calibrated_score(calibration, best):
    one_hot = action_target(SUMS, COUNTS, NEUTRAL, calibration, "argmax")
    assert one_hot.dtype == np.float32 and one_hot.tolist() == np.eye(3)[best].tolist()
    dist = action_target(SUMS, COUNTS, NEUTRAL, calibration, "distribution")
    assert np.array_equal(dist, action_distribution(SUMS, COUNTS, NEUTRAL, calibration))
    assert dist.argmax(-1).tolist() == best
    with pytest.raises(ValueError, match="argmax"):
        action_target(SUMS, COUNTS, NEUTRAL, calibration, "sample")


class _Cache:
    """The two AnnotationCache calls CachedTargets makes; every key but "a2" is found."""

    def refresh(self):
        pass

    def get_matrices(self, keys, columns, *, task):
        found = np.array([k[1:] != "2" for k in keys])
        if task == "summary":
            return {"found": found, "embedding": np.ones((len(keys), 4), np.float32)}
        return {"found": found, **{name: np.tile(np.asarray(value, np.float32), (len(keys), 1)) for name, value in
                                   (("cand_logprob_sum", SUMS[0]), ("cand_token_count", COUNTS[0]),
                                    ("neutral_logprob_sum", NEUTRAL[0]))}}


class _Builder:
    def state_keys(self, record, tasks=("action", "summary")):
        return tuple(f"{t[0]}{record.observation}" for t in tasks)


def test_cached_targets_serve_the_chosen_action_target():
    records = [StateRecord("go to the red ball", (), str(i), ("turn left", "turn right", "go forward"))
               for i in range(3)]
    args = dict(calibration="sum", num_actions=3, embedding_dim=4)
    default = CachedTargets(_Cache(), _Builder(), **args).targets(records)
    paper = CachedTargets(_Cache(), _Builder(), action_target="argmax", **args).targets(records)
    assert default.mask.tolist() == paper.mask.tolist() == [True, True, False]
    assert np.allclose(default.action_probs[0], action_distribution(SUMS[0], COUNTS[0], NEUTRAL[0], "sum"))
    assert paper.action_probs.tolist() == [[0, 1, 0], [0, 1, 0], [0, 0, 0]]
    with pytest.raises(ValueError, match="argmax"):
        CachedTargets(_Cache(), _Builder(), action_target="top1", **args)


def test_action_target_is_validated_in_one_line():
    assert TrainConfig().bonus.action_target == "distribution"
    with pytest.raises(UsageError, match="--action-target") as err:
        TrainConfig.from_dict(dict(action_target="top1"))
    assert "\n" not in str(err.value)


# --- B. the action space: auto resolved where the env is made, and recorded resolved -----------
def test_collect_records_the_resolved_action_space_and_append_keeps_it(tmp_path):
    out = tmp_path / "traj"
    summary = collect(CollectConfig(env_id=ENV, out=out, steps=16, num_envs=2))
    assert summary["action_space"] == "original"
    from illm_tools.data.trajectories import open_table

    rows = open_table(out, columns=["valid_actions"])["valid_actions"].to_pylist()
    assert rows[0] == ["turn left", "turn right", "go forward"] and all(r == rows[0] for r in rows)
    with pytest.raises(UsageError, match="--action-space") as err:
        collect(CollectConfig(env_id=ENV, out=out, steps=4, num_envs=2, action_space="augmented", write="append"))
    assert "\n" not in str(err.value) and open_table(out, columns=["step"]).num_rows == 16
    assert collect(CollectConfig(env_id=ENV, out=out, steps=4, num_envs=2, seed=100, write="append"))["rows"] == 4


def _ppo_config(run_dir, **kw):
    return TrainConfig.from_dict(dict(env_id=ENV, run_dir=run_dir, method="ppo", num_envs=2, num_steps=16, num_minibatches=2,
                       update_epochs=1, tensorboard=False, **kw))


def _train(cfg):
    from illm_tools.rl.run import train

    return train(cfg)  # a resumed run's recorded choices (its action space) kept, as `illm train --resume`


def test_train_records_the_resolved_action_space_and_resumes_it(tmp_path):
    run = tmp_path / "run"
    _train(_ppo_config(run, total_steps=32))
    assert json.loads((run / "config.json").read_text())["action_space"] == "original"
    assert load_checkpoint(run)["config"]["action_space"] == "original"
    _train(_ppo_config(run, total_steps=64, resume=True))  # "auto" again: the run's own space
    assert load_checkpoint(run)["global_step"] == 64


def test_a_run_recorded_as_augmented_resumes_under_auto_and_its_policy_collects(tmp_path):
    run = tmp_path / "old"
    _train(_ppo_config(run, total_steps=32, action_space="augmented"))  # as runs before "auto" were
    _train(_ppo_config(run, total_steps=64, resume=True))
    state = load_checkpoint(run)
    assert state["global_step"] == 64 and state["config"]["action_space"] == "augmented"
    assert len(state["action_names"]) == 6
    with pytest.raises(UsageError, match="action_space"):
        _train(_ppo_config(run, total_steps=96, resume=True, action_space="original"))
    summary = collect(CollectConfig(env_id=ENV, out=tmp_path / "traj", steps=8, num_envs=2, policy=str(run)))
    assert summary["action_space"] == "augmented"


# --- C. the bonus's scale next to the task reward ----------------------------------------------
def _tiny_rollout() -> Rollout:
    ro = Rollout.empty(3, 2, (7, 7, 3), 4)
    ro.rewards[2, 0] = 1.0
    ro.ends[2, 0] = 1.0
    return ro


def test_two_stream_advantages_return_the_weighted_parts_and_their_scale():
    ro, zero = _tiny_rollout(), torch.zeros(2)
    bonus = torch.tensor([[0.5, 0.0], [0.0, 1.0], [0.25, 0.0]])
    kw = dict(gamma=0.5, int_gamma=0.5, lam=1.0, int_episodic=False)
    adv = two_stream_advantages(ro, bonus, zero, zero, ext_coef=2.0, int_coef=3.0, **kw)
    # values are zero, so with lambda 1 the advantages are the discounted returns
    a_ext = torch.tensor([[0.25, 0.0], [0.5, 0.0], [1.0, 0.0]])
    a_int = torch.tensor([[0.5 + 0.0625, 0.5], [0.125, 1.0], [0.25, 0.0]])
    assert torch.allclose(adv.ext_part, 2 * a_ext) and torch.allclose(adv.int_part, 3 * a_int)
    assert torch.allclose(adv.advantages, adv.ext_part + adv.int_part)
    logs = adv.scale_logs()
    assert logs["adv_ext_abs"] == pytest.approx(2 * 1.75 / 6)
    assert logs["adv_int_abs"] == pytest.approx(3 * 2.4375 / 6)
    assert logs["adv_int_ext_ratio"] == pytest.approx(3 * 2.4375 / (2 * 1.75))
    assert logs["return_ext"] == pytest.approx(1.75 / 6) and logs["return_int"] == pytest.approx(2.4375 / 6)

    no_task = two_stream_advantages(Rollout.empty(3, 2, (7, 7, 3), 4), bonus, zero, zero,
                                    ext_coef=1.0, int_coef=1.0, **kw).scale_logs()
    assert no_task["adv_ext_abs"] == 0.0 and np.isfinite(no_task["adv_int_ext_ratio"])
    assert no_task["adv_int_ext_ratio"] == pytest.approx(no_task["adv_int_abs"] / 1e-8)
    plain = two_stream_advantages(ro, None, zero, zero, ext_coef=1.0, int_coef=1.0, **kw).scale_logs()
    assert plain["adv_int_abs"] == plain["adv_int_ext_ratio"] == plain["return_int"] == 0.0


def test_trainer_logs_the_bonus_scale_every_update(tmp_path):
    from fakes import make_trainer

    trainer, _ = make_trainer(tmp_path, updates=1)
    metrics = trainer.train()
    ratio, ext, intr = (metrics[f"charts/{k}"] for k in ("adv_int_ext_ratio", "adv_ext_abs", "adv_int_abs"))
    assert intr > 0 and ratio == pytest.approx(intr / max(ext, 1e-8))
    assert {"charts/return_ext", "charts/return_int"} <= set(metrics)
    row = json.loads((tmp_path / "run" / "metrics.jsonl").read_text().splitlines()[-1])
    assert row["charts/adv_int_ext_ratio"] == metrics["charts/adv_int_ext_ratio"]


def test_bonus_presets_and_explicit_flags_win():
    defaults = {"reward_streams": 2, "action_target": "distribution", "bonus_schedule": "constant", "int_ext_cap": 0.0}
    assert bonus_weights("paper") == {"lambda_a": 0.8, "beta_hc": 0.5, "ext_coef": 1.0, "int_coef": 1.0, **defaults}
    assert bonus_weights("rnd", int_coef=0.5, lambda_a=None) == {"lambda_a": 0.8, "beta_hc": 0.5,
                                                                 "ext_coef": 2.0, "int_coef": 0.5, **defaults}
    assert bonus_weights("small")["int_ext_cap"] == 1.0  # the default's cap (issue 71)
    assert bonus_weights("ngu")["int_coef"] == 0.3  # NGU's r = r_e + beta r_i, beta 0.3 (Badia et al. 2020)
    literal = bonus_weights("paper-literal")  # Algorithm 1: one stream, the argmax action
    assert (literal["reward_streams"], literal["action_target"], literal["lambda_a"]) == (1, "argmax", 0.8)
    assert bonus_weights("paper-literal", reward_streams=2)["reward_streams"] == 2  # explicit settings win
    with pytest.raises(UsageError, match="paper, rnd, ngu, small, paper-literal"):
        bonus_weights("apt")


def test_train_cli_passes_preset_coefficients_and_action_target(tmp_path, monkeypatch):
    import illm_tools.rl.run as run_module
    from cli.main import app

    seen = []
    monkeypatch.setattr(run_module, "train", lambda cfg, on_metrics=None, should_stop=None, started=None: seen.append(cfg) or {})
    result = CliRunner().invoke(app, ["train", "--method", "ppo", "--out", str(tmp_path / "r"), "--frames", "64",
                                      "--bonus-preset", "rnd", "--int-coef", "0.5", "--action-target", "argmax"])
    assert result.exit_code == 0, result.output
    cfg = seen[0]
    assert (cfg.bonus.ext_coef, cfg.bonus.int_coef, cfg.illm.lambda_a, cfg.illm.beta_hc) == (2.0, 0.5, 0.8, 0.5)
    assert cfg.bonus.action_target == "argmax" and cfg.action_space == "auto"
    bad = CliRunner().invoke(app, ["train", "--method", "ppo", "--out", str(tmp_path / "r"), "--action-target", "x"])
    assert bad.exit_code == 1 and "--action-target" in bad.output
