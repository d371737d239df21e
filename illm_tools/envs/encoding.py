"""How each kind of observation becomes a tensor, shared by the policy's torsos
(`illm_tools.rl.networks`) and the bonuses' own encoders (`illm_tools.intrinsic.ngu`, NGU's and
APT's embeddings): MiniGrid's grid codes (the channel sizes of its one-hot encoding), pictures and
stacked frames (channels first, scaled to [0, 1], the Nature CNN trunk), NetHack's glyphs (the
glyph count). Below the trainer and the bonuses, so neither imports the other for it.
"""

from __future__ import annotations

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


def channels_first(images: torch.Tensor, kind: str) -> torch.Tensor:
    """[B, C, H, W] float in [0, 1] from "frames" ([B, C, H, W] uint8) or "image" ([B, H, W, C] uint8)."""
    x = images.float() / 255.0
    return x.permute(0, 3, 1, 2) if kind == "image" else x


def chw_shape(image_shape: tuple[int, ...], kind: str) -> tuple[int, int, int]:
    """(C, H, W) of one "frames" or "image" observation."""
    if kind == "image":
        h, w, c = image_shape
        return c, h, w
    c, h, w = image_shape
    return c, h, w
