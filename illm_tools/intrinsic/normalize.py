"""Reward normalisation shared by the intrinsic bonuses, as in RND (Burda et al. 2018).

An intrinsic reward is divided by a running estimate of the standard deviation of its
*discounted intrinsic return*: a per-env forward filter keeps R_t = r_t + gamma * R_{t-1}
(never reset at episode ends: RND's intrinsic stream is non-episodic), and a RunningMeanStd
(Chan et al. parallel update, float64) tracks the mean/variance of those R_t. Only the scale is
changed; the mean is not subtracted, so a reward of zero stays zero.

`RunningMeanStd` also tracks element-wise moments of arrays (`shape`), as RND's observation
normaliser does.
"""

from __future__ import annotations

import numpy as np
import torch


class RunningMeanStd:
    """Running mean and variance of a stream of samples of `shape` (scalars by default), merged
    batch by batch (Chan et al.'s parallel update, float64). The prior (mean 0, var 1, weight
    `epsilon`) keeps the variance above zero."""

    def __init__(self, epsilon: float = 1e-4, shape: tuple[int, ...] = ()):
        self.shape = tuple(shape)
        self.mean = np.zeros(self.shape) if self.shape else 0.0
        self.var = np.ones(self.shape) if self.shape else 1.0
        self.count = epsilon

    def update(self, x: np.ndarray | torch.Tensor) -> None:
        """Merge a batch of samples: any array or tensor (on any device) whose trailing axes are `shape`."""
        if isinstance(x, torch.Tensor):
            x = x.detach().to("cpu", torch.float64).numpy()
        x = np.asarray(x, dtype=np.float64).reshape(-1, *self.shape)
        if x.shape[0] == 0:
            return
        self.update_from_moments(x.mean(0), x.var(0), x.shape[0])

    def update_from_moments(self, batch_mean, batch_var, batch_count: int) -> None:
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.mean = self.mean + delta * batch_count / total
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        self.var = m2 / total
        self.count = total

    @property
    def std(self) -> float:
        """sqrt(var) of a scalar stream."""
        return float(np.sqrt(self.var))

    def state_dict(self) -> dict:
        # plain floats / nested lists: checkpoints are read with torch.load(weights_only=True)
        return {"mean": np.asarray(self.mean).tolist(), "var": np.asarray(self.var).tolist(), "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        if self.shape:
            self.mean = np.asarray(state["mean"], dtype=np.float64).reshape(self.shape)
            self.var = np.asarray(state["var"], dtype=np.float64).reshape(self.shape)
        else:
            self.mean, self.var = float(state["mean"]), float(state["var"])
        self.count = float(state["count"])


class DiscountedReturnNormalizer:
    """Divides [T, N] intrinsic rewards by the running std of their discounted return.

    `mask` [T, N] marks the steps that carry a reward: unmasked steps add nothing to the return
    (their reward is zero) and are left out of the std estimate, so the scale reflects the bonus
    actually paid.
    """

    def __init__(self, num_envs: int, gamma: float, epsilon: float = 1e-8):
        self.gamma = gamma
        self.epsilon = epsilon
        self.returns = np.zeros(num_envs, dtype=np.float64)
        self.rms = RunningMeanStd()

    def __call__(self, rewards: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        r = rewards.detach().cpu().double().numpy()
        m = np.ones_like(r, dtype=bool) if mask is None else mask.cpu().numpy().astype(bool)
        r = np.where(m, r, 0.0)
        disc = np.empty_like(r)
        for t in range(r.shape[0]):
            self.returns = self.returns * self.gamma + r[t]
            disc[t] = self.returns
        self.rms.update(disc[m])
        scale = np.sqrt(self.rms.var) + self.epsilon
        return (torch.as_tensor(r / scale, dtype=rewards.dtype)).to(rewards.device)

    def state_dict(self) -> dict:
        return {"returns": self.returns.tolist(), "rms": self.rms.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.returns = np.asarray(state["returns"], dtype=np.float64)
        self.rms.load_state_dict(state["rms"])
