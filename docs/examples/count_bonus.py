"""A count-based exploration bonus as an illm plug-in: `illm train --method count`.

Pays scale / sqrt(n) for reaching an observation seen n times in the run so far. One file: the
bonus's settings (a dataclass: each field is a `--bonus-option KEY=VALUE`), the bonus (an
`IntrinsicBonus` subclass: the trainer calls its hooks with the rollout's tensors) and the `Method`
that names it. An installed package declares it as an entry point (see the page this file is
quoted in); tests/test_docs_examples.py trains with it.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import torch

from illm_tools.intrinsic import BonusRewards, IntrinsicBonus
from illm_tools.intrinsic.registry import Method


@dataclass
class CountConfig:
    """The count bonus's settings (`--bonus-option scale=0.5`)."""

    scale: float = 1.0
    """Reward of a never-seen observation."""


class CountBonus(IntrinsicBonus):
    """Pays scale / sqrt(n) for reaching an observation seen n times (counted in `observe`)."""

    config_class = CountConfig

    def __init__(self, config: CountConfig, ctx):
        self.scale = config.scale
        self.counts: Counter[bytes] = Counter()

    def observe(self, step):
        """After every env step: count the observations the envs reached."""
        for image in step["next_images"]:
            self.counts[image.numpy().tobytes()] += 1

    def compute_rewards(self, batch):
        """Once per rollout: reward t for transition t, [T, N] like the rollout."""
        images = batch["next_images"]
        t, n = images.shape[:2]
        seen = torch.tensor([self.counts[x.numpy().tobytes()] for x in images.reshape(t * n, -1)],
                            dtype=torch.float32)
        reward = self.scale / seen.clamp_min(1.0).sqrt().view(t, n)
        return BonusRewards(reward, {"count_distinct": float(len(self.counts))})  # logged under charts/

    def state_dict(self):
        return {"distinct": len(self.counts)}  # saved with every checkpoint

    def load_state_dict(self, state):
        pass  # the counts start afresh on --resume


METHOD = Method("count", "a count-based bonus, scale / sqrt(visits)", CountBonus)
