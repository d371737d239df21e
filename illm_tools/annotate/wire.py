"""The JSON form of a state that a trainer sends `illm serve` (`POST /annotate`): its text fields, and
for a hop state its window, each raw observation as shape, dtype and base64 bytes with its previous
action. `record_to_json` writes it (the trainer's `RemoteLive`); the server reads and checks it
(`illm_tools.serve.parse_state`)."""

from __future__ import annotations

import base64

import numpy as np

from illm_tools.tasks.state import StateRecord


def record_to_json(record: StateRecord) -> dict:
    """A state as the request carries it (the inverse of `parse_state`): its text fields, and for a
    hop state its window: each raw observation (shape, dtype, base64 bytes) and previous action."""
    out = {"mission": record.mission, "history": [list(pair) for pair in record.history],
           "observation": record.observation, "valid_actions": list(record.valid_actions)}
    frames = getattr(record, "frames", ())
    if frames:
        out["frames"] = [{"shape": list(np.shape(f)), "dtype": np.asarray(f).dtype.str,
                          "data": base64.b64encode(np.ascontiguousarray(f).tobytes()).decode()} for f in frames]
        out["prev_actions"] = [int(a) for a in record.prev_actions]
    return out
