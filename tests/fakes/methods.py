"""The checks every registered training method gets (tests/test_methods.py runs them over the registry),
as plain functions so that a method registered only inside a test gets the same ones
(test_example_bonus.py: the docs' example bonus): `bonus_reaches_the_advantages` (its reward reaches the
advantages the loss uses) and `trains_end_to_end` (through `illm train --bonus-option` and `illm eval`)."""

from __future__ import annotations

import csv
import json

import torch

from .cli import cli_ok
from .training import make_trainer, one_update_seen


def bonus_reaches_the_advantages(tmp_path, monkeypatch, method: str, logged_key: str) -> None:
    """The registered `method`'s bonus reaches the advantages the loss uses (GAE is linear in the reward;
    the update step receives exactly the two-stream advantages of the bonus the trainer computed, changed
    by it); it logs `charts/intrinsic_reward` and `logged_key` (its loss), both positive."""
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.rl import gae

    # uncapped (int_ext_cap 0, the method presets' value; TrainConfig's own default is illm's cap 1): the
    # comparison below reads GAE's linearity in the reward, which the cap's rescaling would break
    trainer, _ = make_trainer(tmp_path, mode=method, int_gamma=0.9, int_ext_cap=0.0)
    assert trainer.cfg.pays_bonus and trainer.bonus is not None
    assert (trainer.provider is None) != get_method(method).needs_targets
    ro, records, _, next_values = trainer.collect_rollout()
    trainer.attach_targets(ro, records)
    bonus = trainer.intrinsic_rewards(ro).reward
    assert bonus.shape == (32, 4) and (bonus > 0).any()
    with_bonus = trainer.advantages(ro, bonus, next_values).advantages
    without = trainer.advantages(ro, torch.zeros_like(bonus), next_values).advantages
    # GAE is linear in the reward: the difference is the (gamma_int * lambda)-discounted bonus to go
    expected = torch.zeros_like(bonus)
    running = torch.zeros(bonus.shape[1])
    for t in reversed(range(bonus.shape[0])):
        running = bonus[t] + 0.9 * 0.95 * running  # the intrinsic stream is non-episodic
        expected[t] = running
    assert torch.allclose(with_bonus - without, expected, atol=1e-5)
    assert (with_bonus >= without - 1e-6).all() and (with_bonus > without).any()

    # in the real loop, the update step receives the advantages of the bonus the trainer computed
    seen = one_update_seen(trainer, monkeypatch)
    cfg, ro, adv, nxt, logged = trainer.cfg, seen.ro, seen.adv, seen.next, seen.logged
    assert torch.allclose(adv.advantages, seen.expected.advantages, atol=1e-5)  # the loss saw the bonus ...
    assert not torch.allclose(adv.advantages, seen.without.advantages)       # ... and it changed them
    ext_only, _ = gae(ro.rewards, ro.values_ext, nxt.value_ext, ro.ends, cfg.ppo.gamma, cfg.ppo.gae_lambda)
    assert not torch.allclose(adv.advantages, ext_only) and adv.returns_int.abs().sum() > 0
    assert logged["charts/intrinsic_reward"] > 0 and logged["charts/adv_int_abs"] > 0
    assert logged[logged_key] > 0


def trains_end_to_end(tmp_path, method: str, option: str, loss: str, part: str) -> None:
    """The registered `method` trains through `illm train --bonus-option OPTION` (the option in
    config.json, `loss` logged positive, `part` in its checkpointed bonus state) and `illm eval`
    reads the run."""
    from illm_tools.rl import load_checkpoint

    run = tmp_path / method
    said = cli_ok("train", "--method", method, "--frames", 4096, "--bonus-option", option, "--out", run)
    assert f"trained {method}" in said and "LLM target" not in said
    cfg = json.loads((run / "config.json").read_text())
    key, value = option.split("=")
    assert cfg["method"] == method and cfg["bonus_options"] == {key: type(cfg["bonus_options"][key])(value)}
    if method == "rnd":  # RND's preset by default
        assert (cfg["bonus"]["ext_coef"], cfg["bonus"]["int_coef"]) == (2.0, 1.0)
    with open(run / "metrics.csv", newline="") as fh:
        assert [int(r["global_step"]) for r in csv.DictReader(fh)] == [2048, 4096]
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert all(r["charts/intrinsic_reward"] > 0 and r[loss] > 0 for r in rows)
    assert part in load_checkpoint(run)["bonus"]
    (row,) = json.loads(cli_ok("eval", run, "--episodes", 2, "--json"))
    assert row["method"] == method and row["frames"] == 4096
