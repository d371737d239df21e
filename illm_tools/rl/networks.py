"""The agent's networks: a torso per kind of observation, actor, two critics, iLLM heads.

Owns `GridMissionNet` (features -> actor logits, extrinsic and intrinsic values) and the
heads f^a / f^hc (two fully connected layers of `head_hidden` units on the torso's features:
Linear(F, 1024) - ReLU - Linear(1024, out)). Layout follows rl-starter-files' ACModel, with the
grid's object/colour/state indices one-hot encoded instead of fed as raw numbers.

The other suites' torsos subclass it and replace `build_torso` / `features`: `FrameNet` (the Nature
CNN of Mnih et al. 2015 on Atari's stacked frames or Crafter's picture) and `GlyphNet` (MiniHack's
glyph crop through a learned glyph embedding and a small CNN, and the message bytes through a
byte embedding and a 1-D convolution). `NETWORKS` names them for the suites: a suite says which
torso reads its observations by a plain name (`Suite.network`: "grid-mission", "frame", "glyph"),
which this layer resolves, so no suite names a class up the layers; a plug-in suite may instead give
its own class as "module:Class" (or the class), or register it here (`NETWORKS.register`, or the
`illm.networks` entry point) and give its name. `make_network` picks a run's class: the method's
own network (ChibiT) or else the suite's, refusing a pair whose observation kinds do not fit
(`kinds`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from illm_tools.envs.encoding import GRID_CHANNEL_SIZES, NUM_GLYPHS, PAD, MissionVocab, conv_trunk, layer_init
from illm_tools.errors import UsageError
from illm_tools.registry import Registry, load_class

def mlp_head(inp: int, hidden: int, out: int, *, std: float, act: type[nn.Module] = nn.Tanh) -> nn.Sequential:
    return nn.Sequential(layer_init(nn.Linear(inp, hidden)), act(), layer_init(nn.Linear(hidden, out), std))


class PolicyOutput(NamedTuple):
    logits: torch.Tensor     # [B, A]
    value_ext: torch.Tensor  # [B]
    value_int: torch.Tensor  # [B]
    features: torch.Tensor   # [B, F]


class GridMissionNet(nn.Module):
    """Actor-critic over (symbolic grid, mission) with optional iLLM heads.

    images: uint8/int [B, H, W, 3] MiniGrid encoding; missions: int64 [B, L] from `MissionVocab`;
    `image_shape` is one observation's shape.
    `embedding_dim=None` builds no heads (plain PPO); else one head per language task of `tasks`
    (`illm_tools.tasks.registry`: f_a for action, f_hc for summary, f_goal, f_plan), each of
    `head_hidden` units, the text heads of `embedding_dim` outputs. Subclasses replace the torso
    (`build_torso`, `features`); `Options` lists the settings a torso takes (`--network-option`).
    """

    Options = None
    """The dataclass of this network's settings (None: it has none)."""
    kinds: tuple[str, ...] = ("grid",)
    """The observation kinds (`illm_tools.envs.suite.ObsSpec.kind`) this torso reads."""

    def __init__(self, num_actions: int, *, vocab_size: int, embedding_dim: int | None = None,
                 head_hidden: int = 1024, image_shape: tuple[int, ...] = (7, 7, 3), heads_bf16: bool | None = None,
                 hidden: int = 64, options=None, context_dim: int = 0, tasks: tuple[str, ...] = ("action", "summary"),
                 observation=None):
        super().__init__()
        self.observation = observation  # the suite's adapter (`illm_tools.envs.observations`); torsos read through it
        self.register_buffer("cell_sizes", torch.tensor(GRID_CHANNEL_SIZES), persistent=False)
        self.register_buffer("cell_offsets", torch.tensor(np.cumsum((0, *GRID_CHANNEL_SIZES[:-1]))),
                             persistent=False)
        self.context_dim = int(context_dim)
        self.feature_dim = self.build_torso(vocab_size=vocab_size, image_shape=image_shape,
                                            options=options) + self.context_dim
        self.actor = mlp_head(self.feature_dim, hidden, num_actions, std=0.01)
        self.critic_ext = mlp_head(self.feature_dim, hidden, 1, std=1.0)
        self.critic_int = mlp_head(self.feature_dim, hidden, 1, std=1.0)
        self.f_a = self.f_hc = None
        self.heads_bf16 = (bf16_is_faster() if embedding_dim is not None else False) if heads_bf16 is None \
            else heads_bf16  # measured only for a network with heads
        self.head_tasks: tuple[str, ...] = ()
        self.text_heads: tuple[str, ...] = ()
        if embedding_dim is not None:
            from illm_tools.tasks.registry import get_task

            for task in tasks:  # f_a, then f_hc: the order (and the init) of the paper's two heads
                spec = get_task(task)
                if spec.kind == "ranking" and task != "action":
                    raise ValueError(f"the policy carries one ranking head, the action task's; {task!r} is another")
                out, std = (num_actions, 0.01) if spec.kind == "ranking" else (embedding_dim, 1.0)
                setattr(self, spec.head, mlp_head(self.feature_dim, head_hidden, out, std=std, act=nn.ReLU))
            self.head_tasks = tuple(tasks)
            self.text_heads = tuple(get_task(t).head for t in tasks if get_task(t).kind == "text")

    @property
    def has_heads(self) -> bool:
        return bool(self.head_tasks)

    def build_torso(self, *, vocab_size: int, image_shape: tuple[int, ...], options=None,
                    word_embed: int = 32, text_hidden: int = 128) -> int:
        """The grid CNN and the mission encoder; returns the feature dimension."""
        channels = sum(GRID_CHANNEL_SIZES)
        self.image_conv = nn.Sequential(
            nn.Conv2d(channels, 16, (2, 2)), nn.ReLU(), nn.MaxPool2d((2, 2)),
            nn.Conv2d(16, 32, (2, 2)), nn.ReLU(),
            nn.Conv2d(32, 64, (2, 2)), nn.ReLU(), nn.Flatten(),
        )
        with torch.no_grad():
            image_dim = self.image_conv(torch.zeros(1, channels, *image_shape[:2])).shape[1]
        return image_dim + self.build_mission_encoder(vocab_size, word_embed, text_hidden)

    def build_mission_encoder(self, vocab_size: int, word_embed: int = 32, text_hidden: int = 128) -> int:
        self.word_embedding = nn.Embedding(vocab_size, word_embed, padding_idx=PAD)
        self.text_rnn = nn.GRU(word_embed, text_hidden, batch_first=True)
        return text_hidden

    def one_hot_grid(self, images: torch.Tensor) -> torch.Tensor:
        """[B, C, H, W] one-hot of object, colour and state (out-of-range indices clamped)."""
        idx = torch.minimum(images.long(), self.cell_sizes - 1) + self.cell_offsets  # [B, H, W, 3]
        b, h, w, _ = idx.shape
        x = torch.zeros(b, h, w, int(sum(GRID_CHANNEL_SIZES)), device=idx.device)
        x.scatter_(-1, idx, 1.0)
        return x.permute(0, 3, 1, 2)

    def encode_mission(self, missions: torch.Tensor) -> torch.Tensor:
        """GRU state after the last word. A batch repeats few missions, so only the distinct ones
        go through the GRU (same result, several times faster forward and backward)."""
        first, inverse, _ = distinct(missions)
        unique = missions[first]
        lengths = (unique != PAD).sum(1).clamp_min(1)
        tokens = unique[:, : int(lengths.max())]  # drop all-padding columns
        out, _ = self.text_rnn(self.word_embedding(tokens))
        return out[torch.arange(len(out)), lengths - 1][inverse]

    def features(self, images: torch.Tensor, missions: torch.Tensor) -> torch.Tensor:
        # the one-hot grid (a learned embedding followed by the first conv would be the same linear map)
        return torch.cat([self.image_conv(self.one_hot_grid(images)), self.encode_mission(missions)], dim=1)

    def forward(self, images: torch.Tensor, missions: torch.Tensor, context: torch.Tensor | None = None) -> PolicyOutput:
        """`context` [B, context_dim]: what the network reads beside its torso (iLLM(hop)'s Z_h),
        concatenated to the torso's features; the heads and critics sit on the concatenation."""
        f = self.features(images, missions)
        if self.context_dim:
            f = torch.cat([f, context.to(f.dtype)], dim=1)
        return PolicyOutput(self.actor(f), self.critic_ext(f).squeeze(-1),
                            self.critic_int(f).squeeze(-1), f)

    def heads(self, features: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(f^a logits [B, A] or None without the action task, the text heads' embeddings side by
        side [B, K * D] in task order (f^hc's alone by default) or None without text tasks)."""
        if not self.head_tasks:
            raise RuntimeError("this network was built without iLLM heads (mode ppo)")
        # on a CPU the heads run once per distinct row: a rollout repeats many states (an action that
        # changes nothing, a turn back), so this is about half the bonus pass's rows and a quarter of a
        # minibatch's in BabyAI; the outputs are the same, and so are the gradients (a repeated row's
        # terms reach the torso through one copy of identical features). On CUDA the FLOPs are cheap
        # and the distinct rows' count would wait for the device
        distinct = distinct_rows(features) if features.device.type == "cpu" else None
        x = features if distinct is None else features[distinct[0]]
        # the heads are most of the iLLM update's FLOPs: bf16 matmuls run several times faster on CPUs
        # with AMX (a Sapphire Rapids Xeon here) and ~30x slower on AVX2-only ones (an AMD EPYC here);
        # `heads_bf16=None` lets `bf16_is_faster` decide (the run records the answer). Parameters,
        # gradients and outputs stay float32
        with torch.autocast(features.device.type, dtype=torch.bfloat16,
                            enabled=self.heads_bf16 and features.device.type == "cpu"):
            action = self.f_a(x).float() if self.f_a is not None else None
            texts = [getattr(self, head)(x).float() for head in self.text_heads]
        text = (texts[0] if len(texts) == 1 else torch.cat(texts, dim=-1)) if texts else None
        if distinct is not None:
            action, text = (None if out is None else out[distinct[1]] for out in (action, text))
        return action, text


def row_hash(words: torch.Tensor) -> torch.Tensor:
    """float64 [B] of the integer rows `words` [B, W]: the numbers times fixed random weights (one
    BLAS call). Equal rows hash alike; distinct rows almost never do (`distinct` checks)."""
    weights = torch.randn(words.shape[1], dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    return words.double() @ weights.to(words.device)


def distinct(words: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(first, inverse, counts) of the rows of the 2-D integer tensor `words`: the index of one row of
    each distinct value, each row's place in `first` (`words[first][inverse]` equals `words`), and
    each value's count; `torch.unique(words, dim=0, return_inverse=True, return_counts=True)`'s
    answer, the values in another order. On a CPU the rows are told apart by `row_hash`, checked: a
    collision falls back to `torch.unique(dim=0)`, which sorts whole rows and is the slow part
    (a minibatch's 512 missions of 32 words: 1.5 ms that way, 0.05 ms hashed; sixteen minibatches
    an update). On CUDA, `torch.unique(dim=0)`."""
    hashed = [(row_hash(words), None)] if words.device.type == "cpu" else []  # dim None: a 1-D sort, 55x faster
    for keys, dim in hashed + [(words, 0)]:  # whole rows where two distinct rows hashed alike
        _, inverse, counts = torch.unique(keys, dim=dim, return_inverse=True, return_counts=True)
        first = torch.argsort(inverse, stable=True)[torch.cumsum(counts, 0) - counts]
        if dim == 0 or torch.equal(words[first][inverse], words):
            return first, inverse, counts


def distinct_rows(x: torch.Tensor, multiple: int = 64) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(row indices `first`, one per distinct row of the 2-D `x` and then repeats of the first up to a
    multiple of `multiple`; each row's place in `first`) so that `x[first][inverse]` equals `x` bit
    for bit; None when that would keep (nearly) every row. The padding keeps the matmuls' shapes to a
    few that recur: oneDNN builds a kernel for every new shape, which cost more than the rows saved.
    Rows are told apart by their bits (`distinct`)."""
    n = x.shape[0]
    if n < 2 * multiple:
        return None
    bits = x.detach().contiguous()
    first, inverse, _ = distinct(bits.view(torch.int32) if bits.element_size() == 4 else bits.view(torch.int16))
    padded = -(-len(first) // multiple) * multiple
    return None if padded >= n else (torch.cat([first, first[:1].expand(padded - len(first))]), inverse)


class FrameNet(GridMissionNet):
    """The Nature CNN torso (512 features) on pixels: Atari's 4 stacked grey 84x84 frames ("frames")
    or Crafter's 64x64 RGB picture ("image"); these suites have no instruction, so `missions` is
    not read. Crafter's semantic view ("cells": its ids ending -Semantic-v1) is read here too, as a
    suite names one network for all its ids: each grid part's codes through an 8-wide embedding of
    its own, stacked, then two 3x3 convolutions of 16 channels (as `GlyphNet` reads MiniHack's glyph
    crop, narrower: 0.6 MFLOP a row forward against the Nature CNN's 7.4 on the 64x64 picture, and
    1,144 features), beside each other byte's code through an 8-wide embedding. With 32 channels
    (2.3 MFLOP, 2,152 features) ppo's update on the semantic view cost 1.16 s of 2,048 steps against
    the rollout's 2.10 s (docs/measured.md)."""

    kinds = ("frames", "image", "cells")

    def build_torso(self, *, vocab_size: int, image_shape: tuple[int, ...], options=None, **_) -> int:
        if self.observation.kind == "cells":
            return self._build_cells(self.observation.spec.parts)
        self.trunk, out = conv_trunk(*self.observation.picture_shape, 512)
        return out

    def _build_cells(self, parts: dict[str, tuple[int, ...]]) -> int:
        self.parts = [(name, tuple(shape), int(np.prod(shape))) for name, shape in parts.items()]
        grids = {shape for _, shape, _ in self.parts if len(shape) == 2}
        if len(grids) != 1:
            raise UsageError(f"the cell torso reads grid parts of one shape; the spec's parts are {parts}")
        (self.grid_shape,) = grids
        count = sum(len(shape) == 2 for _, shape, _ in self.parts)
        self.cell_embeddings = nn.ModuleList(nn.Embedding(256, 8) for _ in range(count))
        self.cell_conv = nn.Sequential(nn.Conv2d(8 * count, 16, 3, padding=1), nn.ReLU(),
                                       nn.Conv2d(16, 16, 3, padding=1), nn.ReLU(), nn.Flatten())
        self.code_embedding = nn.Embedding(256, 8)
        codes = sum(size for _, shape, size in self.parts if len(shape) != 2)
        return 16 * int(np.prod(self.grid_shape)) + 8 * codes

    def features(self, images: torch.Tensor, missions: torch.Tensor) -> torch.Tensor:
        if self.observation.kind != "cells":
            return self.trunk(self.observation.picture(images))
        x, at, grids, codes = images.long().clamp(0, 255), 0, [], []
        for _, shape, size in self.parts:
            piece, at = x[:, at:at + size], at + size
            if len(shape) == 2:
                grids.append(self.cell_embeddings[len(grids)](piece.view(-1, *shape)))  # [B, H, W, 8]
            else:
                codes.append(piece)
        cells = [self.cell_conv(torch.cat(grids, -1).permute(0, 3, 1, 2))]
        return torch.cat(cells + ([self.code_embedding(torch.cat(codes, 1)).flatten(1)] if codes else []), dim=1)


class GlyphNet(GridMissionNet):
    """MiniHack's torso: the agent-centred glyph crop through a 32-wide glyph embedding and two 3x3
    convolutions, the message bytes through a 16-wide byte embedding and a 1-D convolution with max
    pooling, concatenated (the "glyphs" kind: a flat int16 array, crop first, `ObsSpec.parts`)."""

    kinds = ("glyphs",)

    def build_torso(self, *, vocab_size: int, image_shape: tuple[int, ...], options=None, **_) -> int:
        parts = self.observation.spec.parts
        self.crop_shape = tuple(parts["glyphs_crop"])
        self.message_len = int(np.prod(parts["message"]))
        self.glyph_embedding = nn.Embedding(NUM_GLYPHS + 1, 32)
        self.glyph_conv = nn.Sequential(nn.Conv2d(32, 32, 3, padding=1), nn.ReLU(),
                                        nn.Conv2d(32, 32, 3, padding=1), nn.ReLU(), nn.Flatten())
        self.byte_embedding = nn.Embedding(256, 16)
        self.message_conv = nn.Sequential(nn.Conv1d(16, 64, 8, stride=4), nn.ReLU(), nn.AdaptiveMaxPool1d(1),
                                          nn.Flatten())
        return 32 * int(np.prod(self.crop_shape)) + 64

    def forward(self, images: torch.Tensor, missions: torch.Tensor,
                context: torch.Tensor | None = None) -> PolicyOutput:
        """`GridMissionNet.forward` once per distinct (observation, mission) row on a CPU, where the
        network reads no context (`once_per_distinct`): a small level's minibatch repeats most of its
        rows (41 distinct of 512 in Room-5x5 under a random policy; 387-483 in MultiRoom-N4 and River,
        where this leaves the rows as they are), and the heads on the 2,656 features are paid once.
        A minibatch's forward and backward, one core: Room-5x5 194 -> 24 ms, River-Monster 187 -> 105,
        MultiRoom-N4-Monster 176 -> 83 (docs/results/measured/glyph-net.txt)."""
        if self.context_dim or images.device.type != "cpu" or len(images) < 128:  # a rollout step's rows: as they are
            return super().forward(images, missions, context)
        rows = torch.cat([images.to(torch.int32), missions.to(torch.int32)], dim=1)  # glyphs and word ids fit
        found = distinct_rows(rows)
        if found is None:
            return super().forward(images, missions)
        first, inverse = found
        return PolicyOutput(*(out[inverse] for out in super().forward(images[first], missions[first])))

    def features(self, images: torch.Tensor, missions: torch.Tensor) -> torch.Tensor:
        """The crop's and the message's features, each computed once per distinct row on a CPU
        (`once_per_distinct`): a minibatch of 512 rows held 4-65 distinct messages and 24-458 distinct
        crops (Room-5x5 to River-Monster, a random policy), and the message's 256 bytes through the
        byte embedding and the 1-D convolution were the larger part of its forward and backward (84-117
        ms against the crop's 55-65 on one core). A rollout step's 16 rows go through as they are:
        finding their few distinct messages cost as much as it saved."""
        cells = int(np.prod(self.crop_shape))
        crop = once_per_distinct(self._crop, images[:, :cells])
        return torch.cat([crop, once_per_distinct(self._message, images[:, cells:cells + self.message_len])], dim=1)

    def _crop(self, glyphs: torch.Tensor) -> torch.Tensor:
        glyphs = glyphs.long().clamp(0, NUM_GLYPHS).view(-1, *self.crop_shape)
        return self.glyph_conv(self.glyph_embedding(glyphs).permute(0, 3, 1, 2))

    def _message(self, message: torch.Tensor) -> torch.Tensor:
        return self.message_conv(self.byte_embedding(message.long().clamp(0, 255)).transpose(1, 2))


def once_per_distinct(fn, rows: torch.Tensor, multiple: int = 64) -> torch.Tensor:
    """`fn(rows)` [B, F] computed on the distinct rows of the 2-D integer `rows` only and spread back:
    the same outputs, and the same gradients (a repeated row's terms reach the weights through one
    copy). On a CPU, where `distinct_rows` finds enough repeats (at least 2 * `multiple` rows, the
    distinct ones padded to a multiple of `multiple`); on CUDA, and for fewer rows, `fn(rows)` as it is."""
    found = distinct_rows(rows, multiple) if rows.device.type == "cpu" else None
    if found is None:
        return fn(rows)
    first, inverse = found
    return fn(rows[first])[inverse]


NETWORKS: Registry = Registry("network", "illm.networks", check=GridMissionNet, instance=False)
"""The policy networks a suite names (`Suite.network`) by plain name -> class (or "module:Class" of
this layer, imported on first use); installed packages add theirs through `illm.networks` entry
points."""
NETWORKS.register("grid-mission", GridMissionNet)
NETWORKS.register("frame", FrameNet)
NETWORKS.register("glyph", GlyphNet)


def network_class(network: str | type, what: str) -> type[GridMissionNet]:
    """The `GridMissionNet` subclass `network` names: a name in `NETWORKS`, a plug-in's
    "module:Class" (the form every suite used before the names; old ones still resolve), or the
    class itself. An unknown name is refused in one line listing the known ones."""
    if isinstance(network, str) and ":" not in network:
        if network not in NETWORKS:
            raise UsageError(f"{what}: {NETWORKS.unknown(network)} (or a plug-in's 'module:Class')")
        return NETWORKS.load(network)
    return load_class(network, GridMissionNet, what)


def make_network(method, env_id: str, num_actions: int, *, image_shape: tuple[int, ...], vocab_size: int,
                 network_options: dict, embedding_dim: int | None, head_hidden: int,
                 heads_bf16: bool | None = None, context_dim: int = 0,
                 tasks: tuple[str, ...] = ("action", "summary")) -> GridMissionNet:
    """The policy network of a run: the method's own class (ChibiT) or else the suite's
    (`network_class` of `Suite.network`), checked to read the suite's kind of observation;
    `network_options` as the class's `Options`."""
    from illm_tools.envs import suite_of

    suite = suite_of(env_id)
    observation = suite.observation(env_id)
    spec = observation.spec
    cls = load_class(method.network, GridMissionNet, f"method {method.name}: network") if method.network else \
        network_class(suite.network, f"suite {suite.name}: network")
    if spec.kind not in cls.kinds:
        raise UsageError(f"--method {method.name}'s network {cls.__name__} reads {', '.join(cls.kinds)} "
                         f"observations; {env_id} gives {spec.kind} ({spec.description}): use another method")
    return cls(num_actions, vocab_size=vocab_size, options=method.network_options(network_options, cls),
               embedding_dim=embedding_dim, head_hidden=head_hidden, image_shape=tuple(image_shape),
               heads_bf16=heads_bf16, context_dim=context_dim, tasks=tuple(tasks), observation=observation)


def bf16_is_faster() -> bool:
    """Whether the heads' bf16 matmuls beat float32 on this CPU (`illm_tools.llm.dtype`: measured
    once per machine; the trainer records the answer in the run's config.json)."""
    from illm_tools.llm.dtype import HEADS_SHAPE, bf16_is_faster as probe

    return probe(HEADS_SHAPE)
