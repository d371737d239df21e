"""A count-based exploration bonus as an illm plug-in: `illm train --method count`.

Pays scale / n ** exponent (1 / sqrt(n) by default) for reaching an observation seen n times in
the run so far, normalised. One file: the bonus's settings (a dataclass: each field is a
`--bonus-option KEY=VALUE`), the bonus (an `IntrinsicBonus` subclass: the trainer calls its hooks
with the rollout's tensors) and the `Method` that names it. An installed package declares it as an
entry point (see the page this file is quoted in); tests/test_docs_examples.py trains with it and
tests/test_example_bonus.py gives it the checks every built-in method gets.

What every bonus that pays does, as the built-in ones (rnd.py, ngu.py, apt.py) do:
- it pays its raw reward through `self.normalised(raw, norm, logs)`: divided by the running std of
  its discounted return (`DiscountedReturnNormalizer`, with the run's `int_gamma`), so that the
  intrinsic stream's scale does not depend on the bonus's own units; without it a raw reward of ~1
  a step outweighs the task's advantages many times over;
- that same call pays zeros when the method says not to (`Method(..., pays_reward=False)`: the
  bonus's models and counts still train, only the advantages are left alone) and logs what it paid,
  `intrinsic_reward` (with `intrinsic_std`), which the run writes as `charts/intrinsic_reward`;
- it checkpoints the normaliser (`state_dict` / `load_state_dict`), so a resumed run pays on the
  same scale.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import torch

from illm_tools.intrinsic import DiscountedReturnNormalizer, IntrinsicBonus
from illm_tools.intrinsic.registry import Method


@dataclass
class CountConfig:
    """The count bonus's settings (`--bonus-option exponent=1`)."""

    exponent: float = 0.5
    """The raw reward is n ** -exponent for an observation seen n times: 0.5, the classic 1 / sqrt(n);
    larger values stop paying for a revisited observation sooner."""
    scale: float = 1.0
    """Raw reward of a never-seen observation: its units only, which the normalisation divides out
    (it moves `charts/count_raw`, not what is paid; the bonus's weight is the run's `--int-coef`)."""


class CountBonus(IntrinsicBonus):
    """Pays scale / n ** exponent for reaching an observation seen n times (counted in `observe`),
    normalised as every built-in bonus's reward."""

    config_class = CountConfig

    def __init__(self, config: CountConfig, ctx):
        self.scale, self.exponent = config.scale, config.exponent
        self.counts: Counter[bytes] = Counter()
        self.reward_norm = DiscountedReturnNormalizer(ctx.num_envs, ctx.int_gamma)

    def observe(self, step):
        """After every env step: count the observations the envs reached."""
        for image in step["next_images"].cpu():
            self.counts[image.numpy().tobytes()] += 1

    @torch.no_grad()
    def compute_rewards(self, batch):
        """Once per rollout: reward t for transition t, [T, N] like the rollout."""
        images = batch["next_images"]
        t, n = images.shape[:2]
        seen = torch.tensor([self.counts[x.numpy().tobytes()] for x in images.cpu().reshape(t * n, -1)],
                            dtype=torch.float32, device=images.device)
        raw = self.scale * seen.clamp_min(1.0).pow(-self.exponent).view(t, n)
        logs = {"count_distinct": float(len(self.counts)), "count_raw": float(raw.mean())}  # logged under charts/
        return self.normalised(raw, self.reward_norm, logs)  # paid normalised (or zeros), intrinsic_reward logged

    def state_dict(self):
        """Saved with every checkpoint: the normaliser (the counts start afresh on --resume)."""
        return {"reward_norm": self.reward_norm.state_dict(), "distinct": len(self.counts)}

    def load_state_dict(self, state):
        self.reward_norm.load_state_dict(state["reward_norm"])


METHOD = Method("count", "a count-based bonus, 1 / sqrt(visits) normalised", CountBonus)
