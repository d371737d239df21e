"""The iLLM bonus, its distillation losses, the RND-style normaliser and the history tracker."""

import numpy as np
import pytest
import torch

from illm_tools.intrinsic import DiscountedReturnNormalizer, ILLMBonus, RunningMeanStd
from illm_tools.tasks.state import HistoryTracker
from illm_tools.intrinsic.illm import action_disagreement, cosine, summary_disagreement
from illm_tools.envs.encoding import MissionVocab
from illm_tools.rl.networks import GridMissionNet


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_running_mean_std_matches_numpy_over_batches():
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, size=n) for n in (5, 17, 1, 40)]
    rms = RunningMeanStd(epsilon=0.0)
    for b in batches:
        rms.update(b)
    allx = np.concatenate(batches)
    assert rms.count == len(allx)
    assert rms.mean == pytest.approx(allx.mean())
    assert rms.var == pytest.approx(allx.var())


def test_normaliser_divides_by_std_of_discounted_return_and_keeps_it_across_rollouts():
    gamma = 0.5
    norm = DiscountedReturnNormalizer(num_envs=2, gamma=gamma, epsilon=0.0)
    norm.rms = RunningMeanStd(epsilon=0.0)
    r1 = torch.tensor([[1.0, 2.0], [1.0, 0.0], [1.0, 4.0]])
    out1 = norm(r1)
    # per env: R_t = r_t + gamma R_{t-1}
    returns1 = np.array([[1.0, 2.0], [1.5, 1.0], [1.75, 4.5]])
    assert np.allclose(out1.numpy(), r1.numpy() / returns1.std())
    r2 = torch.tensor([[2.0, 0.0]])
    out2 = norm(r2)  # the discounted return carries over from the previous rollout
    returns2 = np.array([1.75 * gamma + 2.0, 4.5 * gamma])
    std = np.concatenate([returns1.ravel(), returns2]).std()
    assert np.allclose(out2.numpy(), r2.numpy() / std)
    assert np.allclose(norm.returns, returns2)


def test_normaliser_ignores_steps_without_target():
    norm = DiscountedReturnNormalizer(num_envs=1, gamma=0.0, epsilon=0.0)
    norm.rms = RunningMeanStd(epsilon=0.0)
    r = torch.tensor([[1.0], [5.0], [3.0]])
    mask = torch.tensor([[True], [False], [True]])
    out = norm(r, mask)
    assert out[1, 0] == 0.0
    assert norm.rms.count == 2  # only the two steps with a target enter the std
    assert np.allclose(out.numpy()[[0, 2], 0], np.array([1.0, 3.0]) / np.std([1.0, 3.0]))


def _batch(t=6, n=3, a=4, d=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {
        "action_logits": torch.randn(t, n, a, generator=g),
        "summary": torch.randn(t, n, d, generator=g),
        "target_probs": torch.randn(t, n, a, generator=g).softmax(-1),
        "target_emb": torch.randn(t, n, d, generator=g),
        "target_mask": torch.rand(t, n, generator=g) > 0.3,
    }


def test_disagreements_are_zero_at_a_match_and_bounded():
    p = torch.tensor([[0.7, 0.2, 0.1]])
    for kind in ("tv", "bhattacharyya"):
        assert action_disagreement(p.log(), p, kind).item() == pytest.approx(0.0, abs=1e-6)
        far = action_disagreement(torch.tensor([[-30.0, -30.0, 30.0]]), torch.tensor([[1.0, 0.0, 0.0]]), kind)
        assert far.item() == pytest.approx(1.0, abs=1e-4)
    v = torch.randn(5, 8)
    assert torch.allclose(summary_disagreement(v, 3 * v), torch.zeros(5), atol=1e-6)
    assert torch.allclose(summary_disagreement(v, -v), torch.ones(5))  # 1 - cos = 2, clipped to 1


def test_the_cosine_is_torchs_in_value_and_gradient_zero_rows_included():
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(0)
    pred, target = torch.randn(64, 576, generator=g, dtype=torch.float64), torch.randn(64, 576, generator=g, dtype=torch.float64)
    pred[3], target[5] = 0.0, 0.0  # a zero vector: the eps clamp, as torch's
    mine, ref = pred.clone().requires_grad_(), pred.clone().requires_grad_()
    ours, theirs = cosine(mine, target), F.cosine_similarity(ref, target, dim=-1, eps=1e-8)
    (ours * torch.arange(64.0, dtype=torch.float64)).sum().backward()
    (theirs * torch.arange(64.0, dtype=torch.float64)).sum().backward()
    assert torch.allclose(ours, theirs, atol=1e-12) and torch.allclose(mine.grad, ref.grad, atol=1e-12)


def test_steps_without_target_get_zero_reward_and_are_counted():
    batch = _batch()
    batch["target_probs"][~batch["target_mask"]] = float("nan")  # whatever sits there is ignored
    bonus = ILLMBonus(num_envs=3)
    out = bonus.compute_rewards(batch)
    mask = batch["target_mask"]
    assert torch.all(out.reward[~mask] == 0)
    assert torch.all(out.reward[mask] > 0)
    assert out.logs["no_target_steps"] == float((~mask).sum())
    assert out.logs["target_coverage"] == pytest.approx(mask.float().mean().item())
    assert 0.0 < out.logs["intrinsic_reward_a"] <= 1.0 and 0.0 < out.logs["intrinsic_reward_hc"] <= 1.0


def test_bonus_is_weighted_sum_of_normalised_parts():
    batch = _batch()
    bonus = ILLMBonus(num_envs=3, lambda_a=0.8, beta_hc=0.5)
    ref_a, ref_hc = DiscountedReturnNormalizer(3, 0.99), DiscountedReturnNormalizer(3, 0.99)
    mask = batch["target_mask"]
    r_a = torch.where(mask, action_disagreement(batch["action_logits"], batch["target_probs"]), 0.0)
    r_hc = torch.where(mask, summary_disagreement(batch["summary"], batch["target_emb"]), 0.0)
    expected = 0.8 * ref_a(r_a, mask) + 0.5 * ref_hc(r_hc, mask)
    assert torch.allclose(bonus.compute_rewards(batch).reward, expected)


def test_noreward_mode_pays_nothing_but_still_reports():
    bonus = ILLMBonus(num_envs=3, pays_reward=False)
    out = bonus.compute_rewards(_batch())
    assert torch.all(out.reward == 0)
    assert out.logs["intrinsic_reward_a"] > 0
    assert bonus.norm_a.rms.count < 1  # the normaliser is untouched


def test_no_target_rows_cannot_leak_nan_into_the_loss():
    batch = {k: v.reshape(-1, *v.shape[2:]) for k, v in _batch().items()}
    batch["target_probs"][~batch["target_mask"]] = float("nan")
    batch["target_emb"][~batch["target_mask"]] = float("nan")
    logits = batch["action_logits"].requires_grad_()
    loss, _ = ILLMBonus(num_envs=3).aux_loss(batch)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()


@pytest.mark.parametrize("summary_loss", ["cosine", "mse"])
def test_distillation_loss_decreases_and_trains_the_torso(summary_loss):
    torch.manual_seed(0)
    vocab = MissionVocab()
    net = GridMissionNet(6, vocab_size=len(vocab), embedding_dim=16, head_hidden=64)
    b = 64
    images = torch.randint(0, 6, (b, 7, 7, 3), dtype=torch.uint8)
    missions = torch.as_tensor(vocab.encode(["go to the red ball", "pick up a key"] * (b // 2)))
    targets = {"target_probs": torch.randn(b, 6).mul(3).softmax(-1), "target_emb": torch.randn(b, 16),
               "target_mask": torch.arange(b) % 4 != 0}
    bonus = ILLMBonus(num_envs=1, summary_loss=summary_loss)
    opt = torch.optim.AdamW(net.parameters(), lr=3e-3)
    conv_before = net.image_conv[0].weight.detach().clone()
    losses = []
    for _ in range(40):
        a, s = net.heads(net.features(images, missions))
        loss, logs = bonus.aux_loss({"action_logits": a, "summary": s, **targets})
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert set(logs) == {"distill_action", "distill_summary"}
    assert losses[-1] < 0.6 * losses[0]
    assert not torch.equal(conv_before, net.image_conv[0].weight)  # gradients reached the torso


def test_history_tracker_keeps_last_k_and_restarts_at_episode_end():
    h = HistoryTracker(num_envs=2, k=2, valid_actions=["left", "right", "forward"])
    h.push(["o1", "p1"], [0, 1], [False, False])
    h.push(["o2", "p2"], [2, 2], [False, True])  # env 1's episode ends here
    h.push(["o3", "q1"], [1, 0], [False, False])
    r0, r1 = h.records(["m0", "m1"], ["o4", "q2"])
    assert r0.history == (("o2", "forward"), ("o3", "right"))
    assert r0.observation == "o4" and r0.mission == "m0"
    assert r1.history == (("q1", "left"),)
    assert r0.valid_actions == ("left", "right", "forward")
    assert HistoryTracker(1, 0, ["a"]).records(["m"], ["o"])[0].history == ()


def _heads_and_grads(net, images, missions):
    """The heads' outputs on the observations' features, and the gradients of a loss over them
    with respect to every parameter (the torso's too)."""
    a, s = net.heads(net.features(images, missions))
    weights = torch.linspace(-1, 1, a.shape[0])[:, None]  # each row's terms count differently
    ((a * weights).sum() + (s.square() * weights).sum()).backward()
    grads = {name: p.grad.clone() for name, p in net.named_parameters() if p.grad is not None}
    net.zero_grad()
    return a.detach(), s.detach(), grads


def test_heads_run_once_per_distinct_row_with_the_same_outputs_and_gradients(monkeypatch):
    """On a CPU the heads run on the distinct rows only (`distinct_rows`); the outputs, and the
    gradients reaching the heads and the torso, are those of running them on every row (a repeated
    row's terms reach the torso through one copy of identical features)."""
    import illm_tools.rl.networks as networks

    torch.manual_seed(0)
    vocab = MissionVocab()
    net = GridMissionNet(6, vocab_size=len(vocab), embedding_dim=16, head_hidden=64, heads_bf16=False)
    pick = torch.randint(0, 50, (300,), generator=torch.Generator().manual_seed(1))
    images = torch.randint(0, 6, (50, 7, 7, 3), dtype=torch.uint8)[pick]
    missions = torch.as_tensor(vocab.encode(["go to the red ball", "pick up a key"] * 25))[pick]
    first, inverse = networks.distinct_rows(net.features(images, missions))
    assert len(first) == 64 and int(inverse.max()) < 50
    deduplicated = _heads_and_grads(net, images, missions)
    monkeypatch.setattr(networks, "distinct_rows", lambda x: None)
    every_row = _heads_and_grads(net, images, missions)
    assert torch.allclose(deduplicated[0], every_row[0], atol=1e-6)
    assert torch.allclose(deduplicated[1], every_row[1], atol=1e-6)
    assert deduplicated[2].keys() == every_row[2].keys() and "image_conv.0.weight" in every_row[2]
    for name, grad in every_row[2].items():
        assert torch.allclose(deduplicated[2][name], grad, rtol=1e-4, atol=1e-5), name


def test_distinct_rows_is_exact_when_rows_hash_alike(monkeypatch):
    """A hash collision (here: every row hashes alike) falls back to comparing whole rows."""
    import illm_tools.rl.networks as networks

    x = torch.randn(40, 8)[torch.arange(200) % 40]
    monkeypatch.setattr(networks, "row_hash", lambda words: torch.zeros(len(words), dtype=torch.float64))
    first, inverse = networks.distinct_rows(x)
    assert len(first) == 64 and len(torch.unique(inverse)) == 40 and torch.equal(x[first][inverse], x)


def test_distinct_rows_keeps_every_row_when_deduplication_would_not_pay():
    from illm_tools.rl.networks import distinct_rows

    assert distinct_rows(torch.randn(100, 8).repeat(2, 1)[:127]) is None  # too few rows
    assert distinct_rows(torch.randn(200, 8)) is None                     # all distinct
    assert distinct_rows(torch.randn(150, 8)[torch.arange(160) % 150]) is None  # 150 -> 192 rows: no saving


@pytest.mark.parametrize("collide", [False, True])
def test_missions_go_through_the_gru_once_each_with_the_result_of_every_row(monkeypatch, collide):
    """`encode_mission` runs the GRU on the distinct missions (`distinct`, hashed, or by whole rows
    where two hash alike); each row's encoding, and the GRU's gradients, are those of every row
    through the GRU on its own."""
    import illm_tools.rl.networks as networks

    torch.manual_seed(0)
    vocab = MissionVocab()
    net = GridMissionNet(6, vocab_size=len(vocab), embedding_dim=None)
    texts = ["go to the red ball", "pick up a key", "open the door", "go to the red ball then pick up a key"]
    missions = torch.as_tensor(vocab.encode([texts[i % 4] for i in (0, 3, 1, 1, 2, 0, 3, 3, 2, 0)]))
    if collide:
        monkeypatch.setattr(networks, "row_hash", lambda words: torch.zeros(len(words), dtype=torch.float64))
    first, inverse, counts = networks.distinct(missions)
    assert len(first) == 4 and torch.equal(missions[first][inverse], missions) and counts.sum() == len(missions)
    encoded = net.encode_mission(missions)
    encoded.square().sum().backward()
    grads = {n: p.grad.clone() for n, p in net.text_rnn.named_parameters()}
    net.zero_grad()
    one_by_one = torch.cat([net.encode_mission(missions[i:i + 1]) for i in range(len(missions))])
    one_by_one.square().sum().backward()
    assert torch.allclose(encoded, one_by_one, atol=1e-6)
    for name, p in net.text_rnn.named_parameters():
        assert torch.allclose(grads[name], p.grad, rtol=1e-4, atol=1e-6), name


@pytest.mark.parametrize("covered", [0, 37, 300])
def test_the_heads_run_where_a_step_has_a_target_with_the_bonus_loss_and_gradients_of_every_row(covered):
    """On a CPU the heads run only on the steps with a target (`ILLMBonus.policy_outputs`): the
    rewards, the logs, the distillation loss and every parameter's gradient are those of the heads
    run on every row; with no target at all the heads still get (zero) gradients, so the optimiser
    steps them as before."""
    torch.manual_seed(0)
    vocab = MissionVocab()
    net = GridMissionNet(6, vocab_size=len(vocab), embedding_dim=16, head_hidden=64, heads_bf16=False)
    g = torch.Generator().manual_seed(1)
    images = torch.randint(0, 6, (300, 7, 7, 3), dtype=torch.uint8, generator=g)
    missions = torch.as_tensor(vocab.encode(["go to the red ball", "pick up a key"] * 150))
    mask = torch.zeros(300, dtype=torch.bool)
    mask[torch.randperm(300, generator=g)[:covered]] = True
    targets = {"target_probs": torch.softmax(torch.randn(300, 6, generator=g), -1),
               "target_emb": torch.randn(300, 16, generator=g), "target_mask": mask}

    def run(heads_on_every_row: bool):
        features = net.features(images, missions)
        batch = {"features": features, **targets}
        if heads_on_every_row:
            batch["action_logits"], batch["summary"] = net.heads(features)
        else:
            batch.update(ILLMBonus(10).policy_outputs(net, batch))
        loss, logs = ILLMBonus(10).aux_loss(batch)
        loss.backward()
        grads = {name: p.grad.clone() for name, p in net.named_parameters() if p.grad is not None}
        net.zero_grad()
        shaped = {k: v.detach().reshape(30, 10, *v.shape[1:]) for k, v in batch.items()}
        rewards = ILLMBonus(10).compute_rewards(shaped)
        return loss.detach(), grads, rewards

    selected, every_row = run(False), run(True)
    assert torch.allclose(selected[0], every_row[0], atol=1e-6)
    assert selected[1].keys() == every_row[1].keys() and "f_hc.0.weight" in selected[1]
    for name, grad in every_row[1].items():
        assert torch.allclose(selected[1][name], grad, rtol=1e-4, atol=1e-6), name
    assert torch.allclose(selected[2].reward, every_row[2].reward, atol=1e-6)
    assert selected[2].logs == pytest.approx(every_row[2].logs, abs=1e-6)
    if not covered:
        assert not selected[1]["f_a.0.weight"].any() and not selected[2].reward.any()
