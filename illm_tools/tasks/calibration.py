"""Turning stored candidate log-probs into the LLM's distribution over actions.

The cache keeps raw scores (summed log-prob, token count, log-prob after a neutral prompt), so
the calibration is chosen at training time without re-running the LLM:
- `sum`: the summed log-prob of the candidate's tokens (the paper's ranking);
- `mean`: the mean per token (removes the length penalty of multi-token actions);
- `pmi`: summed log-prob minus the log-prob after a neutral prompt (removes the model's prior
  preference for an action whatever the state; small models' raw rankings collapse onto one
  action: docs/experiments, "Prior probe").

f^a's target is either that distribution (`distribution`, the default) or the one-hot of its
argmax (`argmax`): the paper's Algorithm 1 line 7 and Appendix A pick the action with the highest
log-probability, a_bar = argmax_i LLM(a_i | Z_h, Z_p), and distil that action.
"""

from __future__ import annotations

import numpy as np

CALIBRATIONS = ("sum", "mean", "pmi")
ACTION_TARGETS = ("distribution", "argmax")


def action_scores(logprob_sum, token_count, neutral_sum, calibration: str) -> np.ndarray:
    """Scores per candidate under a calibration; arrays of shape [..., A]."""
    s = np.asarray(logprob_sum, dtype=np.float64)
    if calibration == "sum":
        return s
    if calibration == "mean":
        return s / np.maximum(np.asarray(token_count, dtype=np.float64), 1.0)
    if calibration == "pmi":
        return s - np.asarray(neutral_sum, dtype=np.float64)
    raise ValueError(f"unknown calibration {calibration!r}: use one of {', '.join(CALIBRATIONS)}")


def action_distribution(logprob_sum, token_count, neutral_sum, calibration: str) -> np.ndarray:
    """Softmax of the calibrated scores over the last axis (float32)."""
    z = action_scores(logprob_sum, token_count, neutral_sum, calibration)
    z = z - z.max(axis=-1, keepdims=True)
    p = np.exp(z)
    return (p / p.sum(axis=-1, keepdims=True)).astype(np.float32)


def action_target(logprob_sum, token_count, neutral_sum, calibration: str, kind: str = "distribution") -> np.ndarray:
    """f^a's target over the last axis (float32): `distribution` is `action_distribution`;
    `argmax` the one-hot of the best calibrated score (the paper's choice; ties go to the first)."""
    if kind == "distribution":
        return action_distribution(logprob_sum, token_count, neutral_sum, calibration)
    if kind != "argmax":
        raise ValueError(f"unknown action target {kind!r}: use one of {', '.join(ACTION_TARGETS)}")
    z = action_scores(logprob_sum, token_count, neutral_sum, calibration)
    return np.eye(z.shape[-1], dtype=np.float32)[z.argmax(axis=-1)]
