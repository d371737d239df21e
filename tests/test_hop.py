"""iLLM(hop): the Hopfield translation, hop records and keys, the language tasks on spliced
embeddings and Z_h in the policy (hop runs that annotate, train, resume and evaluate on MiniGrid and
Atari: tests/test_pipeline.py)."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from illm_tools.hop.context import HopContext, HopTracker, hop_records_from_table
from illm_tools.tasks.annotation_setup import hop_renderer
from illm_tools.hop.translate import FrozenHopfield
from illm_tools.tasks.prompts import PromptBuilder

pytestmark = pytest.mark.usefixtures("model_cache_in_tmp")
ACTIONS = ("left", "right", "forward")


def test_translation_is_deterministic_for_a_seed_and_lies_in_the_span_of_the_embeddings():
    emb = torch.randn(50, 8, generator=torch.Generator().manual_seed(1))
    obs, prev = torch.randint(0, 255, (5, 12)), torch.tensor([-1, 0, 1, 2, 0])
    a = FrozenHopfield(emb, 12, 3, seed=7)(obs, prev)
    assert torch.equal(a, FrozenHopfield(emb, 12, 3, seed=7)(obs, prev))
    assert not torch.allclose(a, FrozenHopfield(emb, 12, 3, seed=8)(obs, prev))
    assert not torch.allclose(a, FrozenHopfield(emb, 12, 3, seed=7, beta=20.0)(obs, prev))
    weights = torch.linalg.lstsq(emb.T, a.T).solution  # x = E^T w: in the span of E's rows
    assert torch.allclose(emb.T @ weights, a.T, atol=1e-4)
    lo, hi = emb.min(0).values, emb.max(0).values  # a convex combination stays inside the box of E's rows
    assert bool(((a >= lo - 1e-5) & (a <= hi + 1e-5)).all())
    assert not torch.allclose(FrozenHopfield(emb, 12, 3, seed=7)(obs, torch.tensor([0] * 5)), a)  # actions matter


def _records(frames, history_len=1):
    tracker, out = HopTracker(1, history_len, ACTIONS), []
    for frame, action in frames:
        (record,) = tracker.records(["get out"], [frame])
        out.append(record)
        tracker.push([action], [False])
    return out


def test_hop_keys_change_with_the_observations_and_settings_and_nothing_else():
    frame = np.zeros((4, 4), np.uint8)
    other = frame.copy()
    other[3, 3] = 1
    builder = PromptBuilder(env_id="ALE/Pong-v5", renderer=hop_renderer(0, 1.0, 2), model_fingerprint="fp",
                            model="m", history_len=1)
    base = builder.state_keys(_records([(frame, 0), (frame, 1)])[1])
    assert base == builder.state_keys(_records([(frame.copy(), 0), (frame.copy(), 1)])[1])  # content, not identity
    assert base != builder.state_keys(_records([(frame, 0), (other, 1)])[1])  # the current observation
    assert base != builder.state_keys(_records([(other, 0), (frame, 1)])[1])  # the window's older step
    assert base != builder.state_keys(_records([(frame, 2), (frame, 1)])[1])  # the previous action
    for renderer in (hop_renderer(1, 1.0, 2), hop_renderer(0, 2.0, 2)):  # projection seed, beta
        changed = PromptBuilder(env_id="ALE/Pong-v5", renderer=renderer, model_fingerprint="fp", model="m",
                                history_len=1)
        assert changed.state_keys(_records([(frame, 0), (frame, 1)])[1]) != base
    assert PromptBuilder(env_id="ALE/Pong-v5", renderer=hop_renderer(0, 1.0, 2), model_fingerprint="fp2",
                         model="m", history_len=1).state_keys(_records([(frame, 0), (frame, 1)])[1]) != base


def _multiroom_frames(steps: int = 30):
    """Hop frames and previous actions of a random-policy MultiRoom-N6 episode (what the trainer translates)."""
    from illm_tools.envs import make_env, suite_of

    suite, env = suite_of("MiniGrid-MultiRoom-N6-v0"), make_env("MiniGrid-MultiRoom-N6-v0", render_text=False)
    obs, _ = env.reset(seed=0)
    rng, out, prev = np.random.default_rng(0), [], -1
    for _ in range(steps):
        out.append((suite.hop_input(suite.policy_obs(obs)), prev))
        prev = int(rng.integers(3))
        obs, *_ = env.step(prev)
    return out


def _gaps(embeddings: torch.Tensor, frames, beta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """1 - cos between the translations of each pair of different (frame, previous action) steps,
    and the translation of the frames twice."""
    obs = torch.as_tensor(np.stack([f.reshape(-1) for f, _ in frames]))
    prev = torch.as_tensor([a for _, a in frames])
    hop = FrozenHopfield(embeddings, obs.shape[1], 3, seed=0, beta=beta)
    x = torch.nn.functional.normalize(hop(obs, prev).double(), dim=1)
    pairs = [(i, j) for i in range(len(frames)) for j in range(i + 1, len(frames))
             if not (np.array_equal(frames[i][0], frames[j][0]) and frames[i][1] == frames[j][1])]
    return torch.tensor([1 - float(x[i] @ x[j]) for i, j in pairs]), hop(obs, prev) - hop(obs, prev)


def test_different_observations_translate_apart_and_the_same_one_the_same():
    """At the default beta (HELM's 100) different MultiRoom views translate to different x_t and
    one view always to the same; stand-in embeddings (the stub's 256 x 576)."""
    from illm_tools.llm.stub import StubBackend

    gaps, again = _gaps(StubBackend().input_embeddings(), _multiroom_frames(), FrozenHopfield.__init__.__kwdefaults__["beta"])
    assert float(again.abs().max()) == 0.0
    assert float(gaps.median()) > 0.05


@pytest.mark.slow  # loads SmolLM2-135M's embedding matrix (de-quantised once: about 20 s)
def test_smollm2s_translation_keeps_the_observation_at_beta_100_and_loses_it_at_1(tmp_path, smollm2_cache_env):
    """SmolLM2-135M's real embeddings (49,152 tokens) on MultiRoom-N6: measured with
    experiments/hop_translation.py, 1 - cos between different observations has a median of 1.0 at
    beta 100 and 4e-6 at beta 1 (rounding is about 1e-7). Threshold: 0.05, far from both."""
    from illm_tools.llm.backend import load_backend

    embeddings = load_backend("transformers", "smollm2-135m", dtype="float32").input_embeddings().detach().float()
    frames = _multiroom_frames()
    gaps, again = _gaps(embeddings, frames, 100.0)
    assert float(gaps.median()) > 0.05 and float(again.abs().max()) == 0.0
    assert float(_gaps(embeddings, frames, 1.0)[0].median()) < 1e-4  # HELM's signature default: nearly uniform


def test_crafters_pictures_are_grey_scaled_before_the_translation():
    from illm_tools.envs import suite_of
    from illm_tools.envs.crafter import grey

    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[0, 0] = (255, 0, 0)
    rgb[1, 1] = (255, 255, 255)
    assert grey(rgb).tolist() == [[76, 0], [0, 255]]  # ITU-R 601 luma, as OpenCV's and ALE's grey
    assert suite_of("CrafterReward-v1").hop_frame(rgb).shape == (2, 2)
    frame = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    assert suite_of("MiniGrid-MultiRoom-N6-v0").hop_frame(frame) is frame  # symbolic codes: as they are


def test_z_h_batches_equal_single_windows_and_records_carry_the_window(tiny_lm):
    context = HopContext(tiny_lm, 16, 3, seed=0, beta=1.0)
    tracker = HopTracker(2, 2, ACTIONS)
    rng = np.random.default_rng(0)
    zs = []
    for t in range(4):
        frames = [rng.integers(0, 255, 16, dtype=np.uint8) for _ in range(2)]
        records = tracker.records(["go", "go"], frames)
        assert len(records[0].frames) == min(t, 2) + 1 and records[0].prev_actions[-1] == (-1 if t == 0 else 1)
        zs.append(context.step(tracker))
        tracker.push([1, 1], [False, t == 1])
    assert zs[-1].shape == (2, tiny_lm.hidden_size)
    window = context.window_embeddings(records[0].frames, records[0].prev_actions)
    alone = context.z_h([window])
    assert torch.allclose(alone[0], zs[-1][0], atol=1e-5)


def test_hop_records_from_a_table_match_the_trainer_s(tmp_path):
    from illm_tools.collect import CollectConfig, collect
    from illm_tools.data.trajectories import open_table
    from illm_tools.hop.context import RAW_COLUMNS

    collect(CollectConfig(env_id="BabyAI-GoToLocal-v0", out=tmp_path / "t", steps=30, num_envs=1))
    table = open_table(tmp_path / "t", columns=[*RAW_COLUMNS, "terminated", "truncated"])
    records, _ = hop_records_from_table(table, 2)
    tracker = HopTracker(1, 2, tuple(table["valid_actions"][0].as_py()))
    raws = [np.frombuffer(r, np.uint8).reshape(s) for r, s in zip(table["obs_raw"].to_pylist(),
                                                                   table["obs_shape"].to_pylist())]
    for i, (raw, action) in enumerate(zip(raws, table["action"].to_pylist())):
        (mine,) = tracker.records([table["mission"][i].as_py()], [raw])
        assert mine == records[i]
        tracker.push([action], [bool(table["terminated"][i].as_py() or table["truncated"][i].as_py())])
