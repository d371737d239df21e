"""The frozen Hopfield translation of an observation into the LLM's token-embedding space.

x_t = E^T softmax(beta * cos(E, P [o_t ; a_{t-1}]))  (paper B.1, HELM's FrozenHopfield, Paischer
et al. 2022): o_t is the flattened observation (the suite's raw observation: Atari's newest grey
84x84 frame, Crafter's 64x64x3 picture, MiniGrid's 7x7x3 codes, MiniHack's glyph array), a_{t-1}
the one-hot previous action (zeros at an episode's first step), P a fixed random projection to the
embedding width d with entries ~ N(0, 1/d) drawn from `seed`, E the LLM's frozen input-embedding
matrix [V, d], cos the cosine similarity of the projected query with each token embedding, and
beta an inverse temperature (not the reward weight beta_hc). The result is a convex combination of
token embeddings: it lies in the span (indeed the convex hull) of E's rows. Cosine similarity
ignores the query's scale, so observations need no normalisation.

beta = 100 (`DEFAULT_BETA`) is HELM's experiments' value (ml-jku/helm, config.json "beta": 100);
1 is only the default of its FrozenHopfield class's signature. The cosines of a query with tens of
thousands of token embeddings lie within a few tenths of each other, so at beta = 1 the softmax is
nearly uniform and every observation translates to nearly the same x_t (SmolLM2-135M, MultiRoom-N6:
49,101 effective tokens of 49,152 and 1 - cos between translations of different observations of
1e-6 to 1e-5); at 100 a few dozen tokens carry the weight and different observations translate to
clearly different x_t (`experiments/hop_translation.py` measures both per model and suite).
"""
from __future__ import annotations

import torch

DEFAULT_BETA = 100.0
"""HELM's inverse temperature (its experiments' config.json)."""


class FrozenHopfield(torch.nn.Module):
    """Translate (observation, previous action) batches into [B, d] input embeddings."""

    def __init__(self, embeddings: torch.Tensor, obs_dim: int, num_actions: int, *, seed: int = 0,
                 beta: float = DEFAULT_BETA):
        super().__init__()
        vocab, d = embeddings.shape
        self.obs_dim, self.num_actions, self.seed, self.beta = int(obs_dim), int(num_actions), int(seed), float(beta)
        generator = torch.Generator().manual_seed(self.seed)
        projection = torch.randn(d, self.obs_dim + self.num_actions, generator=generator) / d ** 0.5
        weights = embeddings.detach().float()
        self.register_buffer("projection", projection, persistent=False)
        self.register_buffer("embeddings", weights, persistent=False)
        self.register_buffer("unit", torch.nn.functional.normalize(weights, dim=1), persistent=False)

    @torch.no_grad()
    def forward(self, observations: torch.Tensor, prev_actions: torch.Tensor) -> torch.Tensor:
        """observations [B, ...] (any numeric dtype), prev_actions int [B] (-1: none) -> float32 [B, d]."""
        obs = observations.reshape(observations.shape[0], -1).float()
        if obs.shape[1] != self.obs_dim:
            raise ValueError(f"observations have {obs.shape[1]} values, the projection takes {self.obs_dim}")
        actions = torch.zeros(obs.shape[0], self.num_actions)
        taken = prev_actions >= 0
        actions[taken, prev_actions[taken].long()] = 1.0
        query = torch.nn.functional.normalize(torch.cat([obs, actions], 1) @ self.projection.T, dim=1)
        weights = torch.softmax(self.beta * (query @ self.unit.T), dim=1)
        return weights @ self.embeddings
