"""ChibiT-style policy: the torso is initialised from a pretrained language model's transformer
blocks, with the observation projected into its embedding space (Takagi 2022, "On the Effect of
Pre-training for Transformer in Different Modality on Offline Reinforcement Learning", whose
ChibiT is a small transformer pretrained on Wikipedia; the iLLM paper uses it as a baseline that
brings language pretraining into the policy instead of into a bonus).

Here the blocks are the first `blocks` decoder layers of the embedded LLM (SmolLM2-135M by
default, `--network-option model=...`), with its rotary position embedding and final norm, all
fine-tuned with the policy. Tokens: the one-hot 7x7 grid cut into 3x3 patches by a strided
convolution (9 tokens, as a ViT's patch embedding), then the mission (the grid policy's GRU
encoding, projected), last, so that under the blocks' causal attention it reads every patch; the
feature is the final-norm hidden state of that last token. Actor, critics and (unused) heads are
the grid policy's. No bonus is paid (method `chibit`).

Cost: each block is ~3.5M parameters at width 576; on 2 CPU cores one block makes an update
about 10x slower than the grid policy's (`benchmarks/bonus.py` measures it); `blocks` trades
pretraining depth for speed.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from torch import nn

from illm_tools.errors import UsageError
from illm_tools.llm.registry import DEFAULT_MODEL
from illm_tools.rl.networks import GRID_CHANNEL_SIZES, GridMissionNet


@dataclass
class ChibiTOptions:
    """`illm train --method chibit --network-option KEY=VALUE`."""

    blocks: int = 1
    """Pretrained decoder layers in the torso (from the bottom of the model)."""
    model: str = DEFAULT_MODEL
    """The language model whose blocks initialise the torso (an alias of `illm models`)."""

    def __post_init__(self) -> None:
        if self.blocks < 1:
            raise UsageError(f"network option blocks must be at least 1, got {self.blocks}")


class ChibiTNet(GridMissionNet):
    """`GridMissionNet` with a pretrained-transformer torso (see the module docstring)."""

    Options = ChibiTOptions

    def build_torso(self, *, vocab_size: int, image_shape: tuple[int, int], options=None, **_) -> int:
        from illm_tools.llm.loading import load_model

        options = options or ChibiTOptions()
        lm = load_model(options.model, dtype="float32")
        layers = lm.model.model.layers
        if options.blocks > len(layers):
            raise UsageError(f"network option blocks={options.blocks}: {options.model} has {len(layers)} blocks")
        width = lm.model.config.get_text_config().hidden_size
        self.patches = nn.Conv2d(sum(GRID_CHANNEL_SIZES), width, kernel_size=3, stride=2)
        text = self.build_mission_encoder(vocab_size)
        self.mission_token = nn.Linear(text, width)
        self.blocks = nn.ModuleList(copy.deepcopy(layers[i]) for i in range(options.blocks))
        self.rotary = copy.deepcopy(lm.model.model.rotary_emb)
        self.norm = copy.deepcopy(lm.model.model.norm)
        self.blocks.requires_grad_(True)
        self.norm.requires_grad_(True)
        return width

    def features(self, images: torch.Tensor, missions: torch.Tensor) -> torch.Tensor:
        patches = self.patches(self.one_hot_grid(images)).flatten(2).transpose(1, 2)  # [B, 9, width]
        tokens = torch.cat([patches, self.mission_token(self.encode_mission(missions))[:, None]], dim=1)
        positions = torch.arange(tokens.shape[1], device=tokens.device)[None].expand(tokens.shape[0], -1)
        rotary = self.rotary(tokens, positions)
        for block in self.blocks:
            tokens = block(tokens, attention_mask=None, position_embeddings=rotary)
        return self.norm(tokens[:, -1])
