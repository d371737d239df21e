"""The JSON form of a state that a trainer sends `illm serve` (`POST /annotate`): its text fields, and
for a hop state its window, each raw observation as shape, dtype and base64 bytes with its previous
action. `record_to_json` writes it (the trainer's `RemoteLive`); the server reads and checks it
(`illm_tools.serve.ServerTerms.parse_state`). Both sides also share the protocol's version and how a request
proves it may be served: `Authorization: Bearer TOKEN`, the token from `illm serve --token` and
`illm train --annotator-token`, or from the environment variable `TOKEN_ENV` on either side."""

from __future__ import annotations

import base64

import numpy as np

from illm_tools.tasks.state import StateRecord

PROTOCOL = 2
"""Version of the request format, answered by /stats and checked by a trainer when it starts (2: a
request names its trainer by `client` and `session`, and a token may be required)."""
TOKEN_ENV = "ILLM_SERVE_TOKEN"
"""The environment variable holding the server's token, read by `illm serve` and by its trainers
when no token option is given (a variable keeps it out of `ps` and the shell's history)."""


MIN_TOKEN_CHARS = 16


def check_token(token: str, option: str) -> str:
    """`token` if it can be one (printable ASCII without spaces: it travels in a header; at least
    MIN_TOKEN_CHARS long: it is all that keeps strangers out); else UsageError in one line that
    says how to make one, without repeating the token."""
    from illm_tools.errors import UsageError

    if not (token.isascii() and token.isprintable() and " " not in token) or len(token) < MIN_TOKEN_CHARS:
        raise UsageError(f"{option} (or {TOKEN_ENV}) must be at least {MIN_TOKEN_CHARS} printable characters without "
                         "spaces: make one with `python -c 'import secrets; print(secrets.token_urlsafe(24))'`")
    return token


def auth_headers(token: str | None) -> dict[str, str]:
    """The request headers that carry `token` (none without one)."""
    return {"Authorization": f"Bearer {token}"} if token else {}


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
