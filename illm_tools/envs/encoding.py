"""How each kind of observation becomes a tensor, shared by the policy's torsos
(`illm_tools.rl.networks`) and the bonuses' own encoders (`illm_tools.intrinsic.ngu`, NGU's and
APT's embeddings): MiniGrid's grid codes (the channel sizes of its one-hot encoding), pictures and
stacked frames (the Nature CNN trunk), NetHack's glyphs (the glyph count), missions (`MissionVocab`: the word ids of BabyAI's instruction
grammar, a suite's default `mission_vocab`); the adapters of `illm_tools.envs.observations` build
on them. Below the trainer and the bonuses, so neither imports the other for it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

# Sizes of minigrid's OBJECT_TO_IDX, COLOR_TO_IDX and STATE_TO_IDX.
GRID_CHANNEL_SIZES = (11, 6, 3)

NUM_GLYPHS = 5976
"""NetHack's glyph count (nle.nethack.MAX_GLYPH), the size of the glyph embedding."""


def layer_init(layer: nn.Linear, std: float = float(np.sqrt(2)), bias: float = 0.0) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


def conv_trunk(in_channels: int, height: int, width: int, out: int) -> tuple[nn.Sequential, int]:
    """The Nature CNN (Mnih et al. 2015): 32 8x8/4, 64 4x4/2, 64 3x3/1 convolutions, ReLU, then
    Linear(., out) - ReLU; returns it and `out`. Input: float [B, C, H, W] (84x84 as in the paper;
    any size from 36x36 works, Crafter's 64x64 included)."""
    convs = nn.Sequential(
        nn.Conv2d(in_channels, 32, 8, stride=4), nn.ReLU(),
        nn.Conv2d(32, 64, 4, stride=2), nn.ReLU(),
        nn.Conv2d(64, 64, 3, stride=1), nn.ReLU(), nn.Flatten(),
    )
    with torch.no_grad():
        flat = convs(torch.zeros(1, in_channels, height, width)).shape[1]
    return nn.Sequential(*convs, layer_init(nn.Linear(flat, out)), nn.ReLU()), out


# Words of BabyAI's instruction grammar (minigrid.envs.babyai.core.verifier) and the fixed
# missions of the MiniGrid levels. Order fixes the ids: append only, never reorder.
MISSION_WORDS = (
    "go to the a an pick up put next open then after you and it "
    "red green blue purple yellow grey "
    "ball box key door object wall goal square lava "
    "on your left right in front of behind "
    "get use unlock avoid traverse rooms fetch reach match colour color same as "
    "locked closed opened room corridor"
).split()
PAD, UNK = 0, 1


class MissionVocab:
    """Maps missions to padded word-id arrays: 0 pads, 1 is any word outside the grammar."""

    def __init__(self, max_len: int = 32, words: Sequence[str] = MISSION_WORDS):
        self.max_len = max_len
        self.ids = {w: i + 2 for i, w in enumerate(dict.fromkeys(words))}
        self._memo: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.ids) + 2

    def encode_one(self, mission: str) -> np.ndarray:
        row = self._memo.get(mission)
        if row is None:
            words = re.findall(r"[a-z]+", mission.lower())[: self.max_len]
            row = np.zeros(self.max_len, dtype=np.int64)
            row[: len(words)] = [self.ids.get(w, UNK) for w in words]
            self._memo[mission] = row
        return row

    def encode(self, missions: Sequence[str]) -> np.ndarray:
        """[B, max_len] int64 word ids."""
        return np.stack([self.encode_one(m) for m in missions])
