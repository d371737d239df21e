"""The trainer's fakes: `FakePool` (the EnvPool interface over a toy task), `FakeProvider`
(deterministic LLM targets from a hash of each record), `RefusingProvider` (for methods that must
never ask), `make_trainer` (a small Trainer over them) and `one_update_seen` (what one update was
handed). Used by test_ppo.py, fakes/methods.py, test_bonus_registry.py, test_ngu_apt.py,
test_bonus_shaping.py, test_rnd.py, test_device.py, test_ellm.py, test_fidelity.py and test_report.py."""

from __future__ import annotations

import zlib
from types import SimpleNamespace

import numpy as np

from illm_tools.envs.suite import EpisodeStats

from .prompts import ACTIONS


class FakePool:
    """The EnvPool interface over a toy task: an episode ends after 3-9 steps; 'go forward'
    on the last step succeeds (reward 1). With `positions`, the agent of env i stands at (step, i)."""

    def __init__(self, num_envs, seed=0, positions=False, env_id="BabyAI-GoToLocal-v0"):
        from illm_tools.envs import suite_of

        self.num_envs, self.action_names, self.suite = num_envs, ACTIONS, suite_of(env_id)
        self.rng = np.random.default_rng(seed)
        self.positions = positions

    def _obs(self):
        n = self.num_envs
        obs = SimpleNamespace(
            images=self.rng.integers(0, 6, size=(n, 7, 7, 3)).astype(np.uint8),
            missions=[f"go to the {c} ball" for c in self.colours],
            texts=[f"you see a wall {s} steps forward" for s in self.steps], seeds=np.arange(n),
            steps=self.steps.copy())
        if self.positions:
            obs.positions = np.stack([self.steps, np.arange(n)], 1)
        return obs

    def reset(self):
        self.steps = np.zeros(self.num_envs, np.int64)
        self.lengths = self.rng.integers(3, 10, self.num_envs)
        self.returns = np.zeros(self.num_envs)
        self.colours = self.rng.choice(["red", "blue"], self.num_envs).tolist()
        return self._obs()

    def step(self, actions):
        self.steps += 1
        done = self.steps >= self.lengths
        rewards = (done & (np.asarray(actions) == 2)).astype(np.float32)
        self.returns += rewards
        episodes = [EpisodeStats(int(i), float(self.returns[i]), int(self.steps[i]), bool(rewards[i] > 0))
                    for i in np.flatnonzero(done)]
        for i in np.flatnonzero(done):
            self.steps[i], self.returns[i] = 0, 0.0
            self.lengths[i] = self.rng.integers(3, 10)
        return SimpleNamespace(rewards=rewards, terminated=done, truncated=np.zeros_like(done),
                               obs=self._obs(), episodes=episodes)


class FakeProvider:
    """Deterministic targets from a hash of each record; about one record in four has none."""

    def __init__(self, num_actions, dim):
        self.num_actions, self.dim, self.calls, self.records = num_actions, dim, 0, []

    def targets(self, records):
        from illm_tools.intrinsic import Targets

        self.calls += 1
        self.records.extend(records)
        probs = np.zeros((len(records), self.num_actions), np.float32)
        emb = np.zeros((len(records), self.dim), np.float32)
        mask = np.zeros(len(records), bool)
        for i, r in enumerate(records):
            key = zlib.crc32(repr((r.mission, r.history, r.observation)).encode())
            rng = np.random.default_rng(key)
            probs[i], emb[i], mask[i] = rng.dirichlet(np.ones(self.num_actions)), rng.normal(size=self.dim), key % 4 != 0
        return Targets(probs, emb, mask)

    def stats(self):
        return {"cache_hit_rate": 0.25, "live_annotations": 7}


class RefusingProvider:
    """A provider for methods that must never ask for targets: asking fails the test."""

    def targets(self, records):
        raise AssertionError("ppo mode must not ask for LLM targets")

    def stats(self):
        return {}


def make_trainer(tmp_path, mode="illm", updates=2, pool=None, name="run", **kw):
    """A Trainer of method `mode` for `updates` updates of 4 envs x 32 steps in `tmp_path / name`, over
    `pool` (a `FakePool` by default) and a provider (`FakeProvider`, or for ppo a `RefusingProvider`; a
    method that needs no targets drops it): (trainer, provider). `kw`: settings by their option names
    (lambda_a=..., resume=..., bonus_options=...), over the defaults (the stub's 8-wide embeddings size
    the heads)."""
    from illm_tools.rl import TrainConfig, Trainer

    settings = dict(run_dir=tmp_path / name, method=mode, num_envs=4, num_steps=32, total_steps=4 * 32 * updates,
                    backend="stub", model="stub:8", head_hidden=32, tensorboard=False, update_epochs=2,
                    num_minibatches=2)
    cfg = TrainConfig.from_dict({**settings, **kw})
    pool = pool or FakePool(cfg.num_envs)
    provider = FakeProvider(len(pool.action_names), cfg.embedding_dim) if mode != "ppo" else RefusingProvider()
    return Trainer(cfg.resolved(), pool, provider), provider


def one_update_seen(trainer, monkeypatch) -> SimpleNamespace:
    """One `trainer.train_one_update()` with what its update step was handed: `logged` (its logs), `ro`
    (the rollout), `adv` (the advantages the loss used), `bonus` (the reward the trainer computed), `next`
    (the rollout's bootstrap values, the network not yet updated), and the advantages
    `two_stream_advantages` gives from them with the bonus (`expected`) and without (`without`)."""
    import torch

    from illm_tools.rl import two_stream_advantages

    seen = {}
    real_update, real_rewards = trainer.update, trainer.intrinsic_rewards

    def rewards(ro, *args, **kwargs):
        seen["bonus"] = out = real_rewards(ro, *args, **kwargs)
        return out

    def capture(ro, adv):
        seen.update(ro=ro, adv=adv)
        with torch.no_grad():
            seen["next"] = trainer.net(*trainer._policy_inputs(trainer.obs))
        return real_update(ro, adv)

    with monkeypatch.context() as patch:
        patch.setattr(trainer, "intrinsic_rewards", rewards)
        patch.setattr(trainer, "update", capture)
        logged = trainer.train_one_update()
    cfg, ro, nxt = trainer.cfg, seen["ro"], seen["next"]
    kw = dict(gamma=cfg.ppo.gamma, int_gamma=cfg.bonus.int_gamma, lam=cfg.ppo.gae_lambda, ext_coef=cfg.bonus.ext_coef,
              int_coef=cfg.bonus.int_coef, int_episodic=cfg.bonus.int_episodic, int_ext_cap=cfg.bonus.int_ext_cap)
    return SimpleNamespace(logged=logged, ro=ro, adv=seen["adv"], bonus=seen["bonus"].reward, next=nxt,
                           expected=two_stream_advantages(ro, seen["bonus"].reward, nxt.value_ext, nxt.value_int, **kw),
                           without=two_stream_advantages(ro, None, nxt.value_ext, nxt.value_int, **kw))


