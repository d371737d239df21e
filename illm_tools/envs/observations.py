"""Observation adapters: how one kind of observation array becomes tensors, for the policy's torso
and for every bonus that reads observations (RND's random features, NGU's and APT's learned
embedding), so that neither the networks nor the bonuses branch on the kind.

An adapter is built from a suite's `ObsSpec` (`Suite.observation(env_id)`; by default the adapter
registered under `spec.kind` in `OBSERVATIONS`) and answers:
- `picture_shape` and `picture(x)`: the observation as a float picture [B, C, H, W] in [0, 1], for
  kinds that are pictures (Atari's stacked frames, Crafter's RGB image); None / not implemented
  otherwise. A convolutional torso (`illm_tools.rl.networks.FrameNet`) reads it;
- `rnd_input(x)`: the raw array RND's networks normalise and read (the newest frame of a stack,
  as CleanRL; an image channels first; otherwise the rows as they are), and `rnd_picture`: whether
  that is a picture (convolutional networks) or rows (an MLP on the flattened array);
- `encoder(hidden, out)`: a learned encoder [B, *shape] -> [B, out] (NGU's and APT's embedding f).

A suite with a new kind of observation returns its own adapter from `Suite.observation` (or
registers it here under its kind): the trainer, the networks and the bonuses need no edit.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from illm_tools.envs.encoding import GRID_CHANNEL_SIZES, NUM_GLYPHS, conv_trunk
from illm_tools.errors import UsageError
from illm_tools.registry import Registry


class Observation:
    """The adapter of one kind of observation (see the module docstring); `spec` is the suite's
    `ObsSpec` (shape, dtype, kind, parts)."""

    kind: str = ""
    rnd_picture: bool = False
    """Whether `rnd_input` is a picture [B, C, H, W] (RND's convolutional networks) or rows (MLPs)."""

    def __init__(self, spec) -> None:
        self.spec = spec
        self.shape: tuple[int, ...] = tuple(spec.shape)

    @property
    def picture_shape(self) -> tuple[int, int, int] | None:
        """(C, H, W) of `picture`, or None when the kind is not a picture."""
        return None

    def picture(self, x: torch.Tensor) -> torch.Tensor:
        """[B, *shape] -> float [B, C, H, W] in [0, 1] (picture kinds only)."""
        raise NotImplementedError(f"{self.kind} observations are not pictures")

    def rnd_input(self, x: torch.Tensor) -> torch.Tensor:
        """What RND's networks read of [B, *shape], before its running normalisation (default: the rows)."""
        return x

    def encoder(self, hidden: int, out: int) -> nn.Module:
        """A learned encoder [B, *shape] -> float [B, out] (default: an MLP on the flattened values)."""
        return nn.Sequential(_Float(), nn.Flatten(), nn.Linear(int(np.prod(self.shape)), hidden), nn.ReLU(),
                             nn.Linear(hidden, out))


class _Float(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.float()


class _OneHotGrid(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return one_hot_grid(x)


class _GlyphEmbedding(nn.Module):
    """Each position's glyph (or message byte) through a 4-wide learned embedding, flattened."""

    def __init__(self) -> None:
        super().__init__()
        self.glyphs = nn.Embedding(NUM_GLYPHS + 1, 4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.glyphs(x.long().clamp(0, NUM_GLYPHS)).flatten(1)


def one_hot_grid(images: torch.Tensor) -> torch.Tensor:
    """uint8 [B, H, W, 3] MiniGrid codes -> float32 [B, H * W * 20]: one-hot of each cell's object,
    colour and state (out-of-range codes clamped), as the policy's torso reads the grid."""
    parts = [F.one_hot(images[..., c].long().clamp(0, size - 1), size) for c, size in enumerate(GRID_CHANNEL_SIZES)]
    return torch.cat(parts, -1).flatten(1).float()


class GridObservation(Observation):
    """MiniGrid's (H, W, 3) object / colour / state codes; encoded one-hot into an MLP."""

    kind = "grid"

    def encoder(self, hidden: int, out: int) -> nn.Module:
        if len(self.shape) != 3 or self.shape[-1] != len(GRID_CHANNEL_SIZES):
            raise UsageError(f"the grid encoder reads MiniGrid's (H, W, 3) codes, got {self.shape}")
        inp = int(np.prod(self.shape[:2])) * sum(GRID_CHANNEL_SIZES)
        return nn.Sequential(_OneHotGrid(), nn.Linear(inp, hidden), nn.ReLU(), nn.Linear(hidden, out))


class _Picture(nn.Module):
    def __init__(self, observation: Observation) -> None:
        super().__init__()
        self.observation = observation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.observation.picture(x)


class PictureObservation(Observation):
    """A picture kind: encoded by the Nature CNN (NGU's Atari embedding is a convnet too)."""

    rnd_picture = True

    def encoder(self, hidden: int, out: int) -> nn.Module:
        trunk, width = conv_trunk(*self.picture_shape, hidden)
        return nn.Sequential(_Picture(self), trunk, nn.Linear(width, out))


class FramesObservation(PictureObservation):
    """Stacked grey frames, (C, H, W) uint8 (Atari)."""

    kind = "frames"

    @property
    def picture_shape(self) -> tuple[int, int, int]:
        c, h, w = self.shape
        return c, h, w

    def picture(self, x: torch.Tensor) -> torch.Tensor:
        return x.float() / 255.0

    def rnd_input(self, x: torch.Tensor) -> torch.Tensor:
        return x[:, -1:]  # the newest frame, as CleanRL's RND


class ImageObservation(PictureObservation):
    """An RGB picture, (H, W, 3) uint8 (Crafter)."""

    kind = "image"

    @property
    def picture_shape(self) -> tuple[int, int, int]:
        h, w, c = self.shape
        return c, h, w

    def picture(self, x: torch.Tensor) -> torch.Tensor:
        return x.float().permute(0, 3, 1, 2) / 255.0

    def rnd_input(self, x: torch.Tensor) -> torch.Tensor:
        return x.permute(0, 3, 1, 2)


class GlyphsObservation(Observation):
    """MiniHack's flat int16 array: the glyph crop, then the message bytes (`ObsSpec.parts`); encoded
    through a 4-wide learned embedding per position into an MLP."""

    kind = "glyphs"

    def encoder(self, hidden: int, out: int) -> nn.Module:
        return nn.Sequential(_GlyphEmbedding(), nn.Linear(4 * int(np.prod(self.shape)), hidden), nn.ReLU(),
                             nn.Linear(hidden, out))


class _Codes(nn.Module):
    """Each byte of a flat uint8 array as a code through a 4-wide learned embedding, flattened."""

    def __init__(self) -> None:
        super().__init__()
        self.codes = nn.Embedding(256, 4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.codes(x.long().clamp(0, 255)).flatten(1)


class CellsObservation(Observation):
    """A flat uint8 array of named parts (`ObsSpec.parts`), every byte a code: 2-D parts are grids
    of cells (Crafter's semantic view: each cell's material and object), 1-D parts codes or counts
    (its inventory, the daylight). The rows as they are for RND; encoded through a 4-wide learned
    embedding of each byte into an MLP, as the glyphs are."""

    kind = "cells"

    def encoder(self, hidden: int, out: int) -> nn.Module:
        return nn.Sequential(_Codes(), nn.Linear(4 * int(np.prod(self.shape)), hidden), nn.ReLU(),
                             nn.Linear(hidden, out))


OBSERVATIONS: Registry = Registry("observation kind", "illm.observations", check=Observation, instance=False)
"""Observation kind (`ObsSpec.kind`) -> its `Observation` class, the default adapter of a suite."""
for _cls in (GridObservation, FramesObservation, ImageObservation, GlyphsObservation, CellsObservation):
    OBSERVATIONS.register(_cls.kind, _cls)


def observation_of(spec) -> Observation:
    """The registered adapter of `spec.kind`, built on `spec` (an unknown kind: one line naming the known)."""
    return OBSERVATIONS.load(spec.kind)(spec)
