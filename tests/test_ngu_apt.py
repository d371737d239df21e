"""NGU and APT (exploration baselines behind the plug-in contract), and the illm-shuffled control.

NGU: episodic novelty falls on a state seen again in the same episode and comes back after a reset,
scaled by RND's life-long factor; APT: a batch of one state pays nothing. Both are deterministic for
a seed, resume their own state and refuse bad settings in one line (that their bonus reaches the
advantages and that they train end to end through `illm train`: tests/test_methods.py, for every
method). illm-shuffled: each state's targets are another
cached state's, fixed across calls and copies of the cache, never its own."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from cli.main import app
from illm_tools.tasks.annotation_setup import AnnotationSetup
from illm_tools.annotate.engine import Annotator
from illm_tools.cache.store import AnnotationCache
from illm_tools.errors import UsageError
from illm_tools.intrinsic import BonusContext, ILLMBonus, RNDBonus
from illm_tools.intrinsic.apt import APTBonus, APTConfig
from illm_tools.intrinsic.ngu import NGUBonus, NGUConfig
from illm_tools.intrinsic.registry import METHODS, get_method
from illm_tools.llm.stub import StubBackend
from illm_tools.rl import TrainConfig, Trainer, load_checkpoint
from illm_tools.rl.live import SyncLive
from illm_tools.rl.targets import CachedTargets
from illm_tools.tasks.state import StateRecord
from fakes import ACTIONS, FakePool, make_trainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CTX = BonusContext(num_envs=4, num_steps=16, image_shape=(7, 7, 3), num_actions=3, feature_dim=8,
                   int_gamma=0.99, seed=0)


def views(count: int, seed: int) -> torch.Tensor:
    """`count` random MiniGrid-like views (object, colour, state codes)."""
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 6, (count, 7, 7, 3), generator=g, dtype=torch.uint8)


def rollout(frames: torch.Tensor, ends: torch.Tensor | None = None, seed: int = 0) -> dict:
    """A [T, N] rollout whose observations are `frames` [T + 1, N, 7, 7, 3] (x_0 .. x_T)."""
    t, n = frames.shape[0] - 1, frames.shape[1]
    actions = torch.randint(0, 3, (t, n), generator=torch.Generator().manual_seed(seed))
    return {"images": frames[:-1], "next_images": frames[1:], "actions": actions,
            "ends": torch.zeros(t, n) if ends is None else ends}


# --- NGU ------------------------------------------------------------------------------------------
def test_ngu_novelty_falls_within_an_episode_and_comes_back_after_its_end():
    torch.manual_seed(0)
    bonus = NGUBonus(NGUConfig(lifelong=False), CTX)
    same, distinct = views(1, seed=1), views(17, seed=2)
    frames = torch.empty(17, 4, 7, 7, 3, dtype=torch.uint8)
    frames[:, 0] = same                 # env 0: one state, again and again
    frames[:, 1] = distinct             # env 1: a new state every step
    frames[:, 2] = same                 # env 2: one state, its episode ends at step 7
    frames[:, 3] = views(17, seed=3)
    ends = torch.zeros(16, 4)
    ends[7, 2] = 1.0
    emb = bonus.embedding
    first = rollout(frames, ends)
    r = bonus.episodic_rewards(emb(first["images"]), emb(first["next_images"]), ends)
    assert r.shape == (16, 4)
    # env 0: the memory holds 1, 2, ... copies of the state at distance 0: 1 / (sqrt(min(n, k)) + c)
    c = bonus.config.pseudo_count
    expected = 1.0 / (torch.arange(1, 17).clamp(max=10).float().sqrt() + c)
    assert torch.allclose(r[:, 0], expected, atol=1e-5)
    assert (r[1:, 1] > 3 * r[1:, 0]).all()                        # new states stay novel
    assert r[7, 2] == 0 and r[8, 2] == pytest.approx(1 / (1 + c))  # ended: the memory restarts
    assert r[8, 2] > r[6, 2]
    assert [len(m) for m in bonus.memory] == [16, 16, 8, 16]  # the ongoing episodes
    # the next rollout continues the same episodes: env 0's state is still no news
    r2 = bonus.episodic_rewards(emb(first["images"]), emb(first["next_images"]), torch.zeros(16, 4))
    assert torch.allclose(r2[:, 0], expected[-1].expand(16), atol=1e-5)
    assert [len(m) for m in bonus.memory] == [32, 32, 24, 32]
    small = NGUBonus(NGUConfig(lifelong=False, k=2, memory_capacity=4), CTX)
    small.episodic_rewards(emb(first["images"]), emb(first["next_images"]), ends)
    assert [len(m) for m in small.memory] == [4, 4, 4, 4]


@pytest.mark.slow  # among the fast tier's longest on a 2-core EPYC: the tier keeps under 2 minutes
def test_ngu_scales_by_rnd_life_long_factor_and_trains_both_models():
    torch.manual_seed(0)
    bonus = NGUBonus(NGUConfig(), CTX)
    assert isinstance(bonus.rnd, RNDBonus)  # rnd.py's networks, normalisation and training, reused
    frames = views(17 * 4, seed=4).view(17, 4, 7, 7, 3)
    batch = rollout(frames)
    emb_before = {k: v.clone() for k, v in bonus.embedding.state_dict().items()}
    out = bonus.compute_rewards(batch)
    assert out.reward.shape == (16, 4) and (out.reward > 0).all()
    assert 1.0 <= out.logs["ngu_lifelong"] <= 5.0 and out.logs["rnd_error"] > 0
    factor, _ = NGUBonus(NGUConfig(), CTX).lifelong_factor(batch["next_images"])
    assert factor.min() >= 1.0 and factor.max() <= 5.0 and factor.max() > 1.0
    logs = bonus.update(batch)
    assert logs["ngu_embedding_loss"] > 0 and logs["rnd_predictor_loss"] > 0
    assert not all(torch.equal(v, emb_before[k]) for k, v in bonus.embedding.state_dict().items())
    # the inverse model learns to tell the actions apart on transitions it has seen
    losses = [bonus.update(batch)["ngu_embedding_loss"] for _ in range(30)]
    assert losses[-1] < 0.5 * logs["ngu_embedding_loss"]


# --- APT ------------------------------------------------------------------------------------------
def test_apt_pays_nothing_for_a_batch_of_one_state_and_more_for_spread_states():
    torch.manual_seed(0)
    bonus = APTBonus(APTConfig(), CTX)
    one = rollout(views(1, seed=5).expand(17, 4, 7, 7, 3).contiguous())
    out = bonus.compute_rewards(one)
    assert out.logs["apt_entropy"] == 0 and torch.equal(out.reward, torch.zeros(16, 4))
    spread = rollout(views(17 * 4, seed=6).view(17, 4, 7, 7, 3))
    out = bonus.compute_rewards(spread)
    assert out.logs["apt_entropy"] > 0.1 and (out.reward > 0).all()
    # a point is not its own neighbour: with every state in the batch twice, k = 1 pays 0, k = 2 does not
    twice = bonus.embedding(views(32, seed=7).repeat(2, 1, 1, 1).view(16, 4, 7, 7, 3))
    assert torch.equal(APTBonus(APTConfig(k=1), CTX).entropy_rewards(twice), torch.zeros(16, 4))
    assert (APTBonus(APTConfig(k=2), CTX).entropy_rewards(twice) > 0).all()
    assert bonus.update(spread)["apt_embedding_loss"] > 0


# --- both, through the trainer --------------------------------------------------------------------
def _comparable(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if not k.startswith("time/") and k != "charts/sps"}


@pytest.mark.parametrize("mode", [pytest.param("ngu", marks=pytest.mark.slow), "apt"])
def test_a_run_is_deterministic_for_a_seed(tmp_path, mode):
    runs = []
    for name in ("a", "b"):
        rows = []
        trainer, _ = make_trainer(tmp_path, mode, name=name, seed=3)
        trainer.on_metrics = rows.append
        trainer.train()
        runs.append([_comparable(r) for r in rows])
    assert len(runs[0]) == 2 and runs[0] == runs[1]
    other, _ = make_trainer(tmp_path, mode, name="c", seed=4)
    assert _comparable(other.train()) != runs[0][-1]


@pytest.mark.parametrize("mode", ["ngu", "apt"])
def test_checkpoints_resume_the_bonus_state(tmp_path, mode):
    trainer, _ = make_trainer(tmp_path, mode, updates=2, checkpoint_every=1)
    trainer.train()
    saved = load_checkpoint(trainer.cfg.run_dir)["bonus"]
    resumed, _ = make_trainer(tmp_path, mode, updates=3, resume=True, checkpoint_every=1)
    before, state = trainer.bonus.state_dict(), resumed.bonus.state_dict()
    assert set(state) == set(before) == set(saved)
    assert all(torch.equal(state["embedding"][k], before["embedding"][k]) for k in before["embedding"])
    opt_a, opt_b = state["optimizer"]["state"], before["optimizer"]["state"]
    assert opt_b and all(torch.equal(opt_a[i]["exp_avg"], opt_b[i]["exp_avg"]) for i in opt_b)
    for part in ("dist_rms", "reward_norm"):
        assert state[part] == before[part] == saved[part], part
    assert torch.equal(state["generator"], before["generator"])
    if mode == "ngu":
        assert state["error_rms"] == before["error_rms"]
        assert all(torch.equal(state["rnd"]["predictor"][k], v) for k, v in before["rnd"]["predictor"].items())
        assert state["rnd"]["obs_rms"] == before["rnd"]["obs_rms"]
        # the environments restart their episodes on resume: so do the episodic memories
        assert any(len(m) for m in trainer.bonus.memory) and not any(len(m) for m in resumed.bonus.memory)
    resumed.train()
    assert load_checkpoint(trainer.cfg.run_dir)["global_step"] == 384


def test_bad_settings_are_refused_in_one_line(tmp_path):
    cases = [
        (lambda: TrainConfig(method="ngu", bonus_options={"k": 40, "memory_capacity": 30}), "larger than"),
        (lambda: TrainConfig(method="ngu", bonus_options={"k": 0}), "must be positive"),
        (lambda: TrainConfig(method="ngu", bonus_options={"max_modulation": 0.5}), ">= 1"),
        (lambda: TrainConfig(method="apt", bonus_options={"k": 0}), "must be positive"),
        (lambda: make_trainer(tmp_path, "apt", bonus_options={"k": 128}),
         "larger than the 127 other states of a rollout"),
        (lambda: TrainConfig(method="rnd", bonus_options={"k": 5}), "rnd has no bonus option k"),
        (lambda: TrainConfig(method="ppo", bonus_options={"k": 5}), "ppo has no bonus option k"),
        (lambda: TrainConfig(method="ngu", bonus_options={"knn_clip": 0.1}), "ngu has no bonus option knn_clip"),
        (lambda: TrainConfig(method="apt", bonus_options={"kernel_epsilon": 0.1}), "apt has no bonus option"),
        (lambda: TrainConfig(method="apt", bonus_options={"k": "many"}), "k must be int"),
    ]
    for make, match in cases:
        with pytest.raises(UsageError, match=match) as err:
            make()
        assert "\n" not in str(err.value)
    trainer, _ = make_trainer(tmp_path, "apt", name="ok", bonus_options={"k": 127})
    assert trainer.bonus.config.k == 127
    result = CliRunner().invoke(app, ["train", "--method", "apt", "--bonus-option", "kernel_epsilon=1",
                                      "--out", str(tmp_path / "cli")])
    assert result.exit_code == 1 and "no bonus option kernel_epsilon" in result.output
    assert len(result.output.strip().splitlines()) == 1


# --- illm-shuffled --------------------------------------------------------------------------------
ENV, RENDERER, DIM = "BabyAI-GoToLocal-v0", "babyai-text@1", 16


def states(count: int, start: int = 0, actions=ACTIONS) -> list[StateRecord]:
    return [StateRecord("go to the red ball", (("You see a wall 3 steps forward", "turn left"),),
                        f"You see a red ball {k} steps forward", tuple(actions)) for k in range(start, start + count)]


def annotate(cache: AnnotationCache, records, *, chunk: int = 4, lm=None) -> Annotator:
    annotator = Annotator(lm or StubBackend(f"synthetic:{DIM}"), cache, model="synthetic", history_len=3, chunk=chunk)
    annotator.annotate_states(records, ENV, RENDERER)
    return annotator


def providers(cache: AnnotationCache, annotator: Annotator, seed: int = 0):
    kw = dict(calibration="sum", num_actions=len(ACTIONS), embedding_dim=DIM)
    builder = annotator.builder(ENV, RENDERER)
    return CachedTargets(cache, builder, **kw), CachedTargets(cache, builder, shuffle_seed=seed, **kw)


def partners(plain: CachedTargets, shuffled: CachedTargets, records) -> list[int]:
    """For each record, the index of the record whose own targets it was given (-1: none)."""
    own, given = plain.targets(records), shuffled.targets(records)
    out = []
    for i in range(len(records)):
        if not given.mask[i]:
            out.append(-1)
            continue
        (j,) = np.flatnonzero((own.embeddings == given.embeddings[i]).all(1))  # both targets: the same state's
        assert np.array_equal(own.action_probs[j], given.action_probs[i])
        out.append(int(j))
    return out


def test_shuffled_targets_are_another_cached_states_fixed_across_calls_and_copies(tmp_path):
    records = states(12)
    cache = AnnotationCache(tmp_path / "ann")
    annotator = annotate(cache, records)
    plain, shuffled = providers(cache, annotator)
    mapping = partners(plain, shuffled, records)
    assert sorted(mapping) == list(range(12)) and all(j != i for i, j in enumerate(mapping))  # a derangement
    seen, i = set(), 0
    for _ in range(12):  # one cycle through the cached states
        seen.add(i)
        i = mapping[i]
    assert len(seen) == 12 and i == 0
    assert partners(plain, shuffled, records) == mapping                  # fixed across calls
    assert shuffled.stats()["target_coverage"] == 1.0 and shuffled.stats()["cache_hit_rate"] == 1.0
    # a copy of the cache written in another order, in other shards: the same permutation
    other = AnnotationCache(tmp_path / "other")
    other_annotator = annotate(other, records[::-1], chunk=5)
    assert partners(*providers(other, other_annotator), records) == mapping
    assert partners(*providers(cache, annotator, seed=1), records) != mapping  # the seed chooses it
    # a state the cache lacks gets no target, as with iLLM
    given = shuffled.targets(records[:2] + states(1, start=50))
    assert given.mask.tolist() == [True, True, False]


def test_shuffled_pool_is_one_setup_and_grows_without_moving_other_states(tmp_path):
    records = states(12)
    cache = AnnotationCache(tmp_path / "ann")
    annotator = annotate(cache, records)
    annotate(cache, states(6, start=100), lm=StubBackend(f"another-model:{DIM}"))  # another setup: never a partner
    plain, shuffled = providers(cache, annotator)
    before = partners(plain, shuffled, records)
    assert sorted(before) == list(range(12))
    # the cache grows: each new entry changes the partner of one state (its predecessor) and of no other
    annotate(cache, states(3, start=12))
    grown = records + states(3, start=12)
    after = partners(plain, shuffled, grown)
    assert sorted(after) == list(range(15)) and all(j != i for i, j in enumerate(after))
    assert sum(before[i] != after[i] for i in range(12)) <= 3


def test_an_action_partner_has_the_same_valid_actions(tmp_path):
    six, three = states(6), states(6, start=20, actions=ACTIONS[:3])
    cache = AnnotationCache(tmp_path / "ann")
    annotator = annotate(cache, six + three)
    builder = annotator.builder(ENV, RENDERER)
    for group, n in ((six, 6), (three, 3)):
        kw = dict(calibration="sum", num_actions=n, embedding_dim=DIM)
        own = CachedTargets(cache, builder, **kw).targets(group).action_probs
        given = CachedTargets(cache, builder, shuffle_seed=0, **kw).targets(group)
        assert given.mask.all() and given.action_probs.shape == (6, n)
        mapping = [int(np.flatnonzero((own == row).all(1))[0]) for row in given.action_probs]
        assert sorted(mapping) == list(range(6)) and all(j != i for i, j in enumerate(mapping))


def test_illm_shuffled_is_illm_on_shuffled_targets_end_to_end(tmp_path, monkeypatch):
    from illm_tools.rl.run import make_provider

    method = get_method("illm-shuffled")
    assert method.bonus_class is ILLMBonus and method.needs_targets and method.policy_heads and method.pays
    assert method.target_shuffle == 0
    assert all(m.target_shuffle is None for name, m in METHODS.items() if name != "illm-shuffled")

    # pass 1 (illm, live annotation by the synthetic annotator) fills the cache with the states a
    # run of this seed meets first; pass 2 (illm-shuffled, cache only) meets them again
    cache = AnnotationCache(tmp_path / "ann")
    annotator = Annotator(StubBackend(f"synthetic:{DIM}"), cache, model=f"synthetic:{DIM}", history_len=3, chunk=64)
    plain = CachedTargets(cache, annotator.builder(ENV, RENDERER), calibration="sum", num_actions=6,
                          embedding_dim=DIM, live=SyncLive(annotator, AnnotationSetup(ENV, RENDERER), budget=10**6))
    common = dict(num_envs=4, num_steps=32, total_steps=128, tensorboard=False, update_epochs=1, num_minibatches=2,
                  head_hidden=32, cache=tmp_path / "ann", model=f"synthetic:{DIM}", backend="stub",
                  live_budget=0)
    Trainer(TrainConfig.from_dict({"run_dir": tmp_path / "fill", "method": "illm", **common}).resolved(), FakePool(4), plain).train()

    cfg = TrainConfig.from_dict({"run_dir": tmp_path / "shuffled", "method": "illm-shuffled", **common})
    provider = make_provider(cfg, len(ACTIONS))
    assert provider.shuffle is not None and provider.shuffle.seed == 0
    assert make_provider(TrainConfig.from_dict({"method": "illm", **common}), len(ACTIONS)).shuffle is None
    trainer = Trainer(cfg.resolved(), FakePool(4), provider)
    assert isinstance(trainer.bonus, ILLMBonus) and trainer.net.has_heads
    looked_up, real_targets = [], provider.targets
    monkeypatch.setattr(provider, "targets", lambda records: looked_up.extend(records) or real_targets(records))
    metrics = trainer.train()
    assert metrics["charts/target_coverage"] == 1.0 and metrics["charts/intrinsic_reward"] > 0
    assert metrics["losses/distill_action"] > 0
    own, given = plain.targets(looked_up), real_targets(looked_up)
    assert given.mask.all() and not (own.embeddings == given.embeddings).all(1).any()  # never its own


def test_copying_the_cache_keeps_the_permutation(tmp_path):
    records = states(8)
    cache = AnnotationCache(tmp_path / "ann")
    annotator = annotate(cache, records, chunk=3)
    mapping = partners(*providers(cache, annotator), records)
    shutil.copytree(tmp_path / "ann", tmp_path / "copy")
    copy = AnnotationCache(tmp_path / "copy")
    assert partners(*providers(copy, annotator), records) == mapping


def test_an_embedding_saved_before_the_observation_adapters_still_loads():
    """Checkpoints named the grid encoder's layers embed.0 / embed.2 (no input module then)."""
    from illm_tools.intrinsic.ngu import InverseDynamics

    model = InverseDynamics(CTX.observation, 3, 16, 8)
    old = {(f"embed.{int(k.split('.')[1]) - 1}." + k.split(".", 2)[2]) if k.startswith("embed.") else k: v
           for k, v in model.state_dict().items()}
    assert "embed.0.weight" in old
    fresh = InverseDynamics(CTX.observation, 3, 16, 8)
    fresh.load_state_dict(old)
    assert all(torch.equal(a, b) for a, b in zip(fresh.state_dict().values(), model.state_dict().values()))
