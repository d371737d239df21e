"""`illm serve`: one loaded LLM answering the live-annotation requests of many `illm train` runs.

A trainer started with `--annotator http://HOST:PORT` posts, after each rollout, the states its
cache lookup missed (most visited first, with their visit counts) instead of handing them to a
worker of its own; the server annotates them through the same `Annotator` and cache API as
`illm annotate`, under its own setup (model, history, layout, tasks, hop settings), so the answers
land in the shared cache, where the trainer finds them on a later rollout (it never waits; with
`--live-mode sync` its request asks to be answered once they have landed, and the same rollout uses
them). One model in memory serves every trainer.

The package, one concern a module:
- `config`: `ServeConfig` (the options) and `ServeLimits` (every limit, each an option), the
  listening address and token checks (a token carries at least 128 bits);
- `protocol`: a request read and checked whole on arrival against the server's own setup
  (`ServerTerms`: text sizes, history, valid actions, a hop frame's shape and dtype, the backend's
  own check; a declared setup other than the server's is refused naming the difference);
- `quotas`: who may be queued, wait or add states (per client name and peer, per peer, in all, room
  kept for new peers, a session tied to its peer while it has states queued or waiting), checked
  before any state of a request is read;
- `intake`: a request's way into the queue, one sequence of checks cheapest first (its fields and
  the trainer quotas, its states parsed, the queue quotas, its states measured in tokens), the
  costly steps in one checking thread off the event loop;
- `scheduler`: `AnnotationServer`, the queue (per-trainer lists), round-robin across clients, the
  waits (one per trainer, cancelled when the client goes), the batch with its deadline and a
  failing state isolated from the others;
- `batch`: a batch's fair order (`take_turns`) and its way through the annotator in a thread;
- `memory`: the process's resident size and the freed memory handed back to the system;
- `http`: aiohttp behind a gate of our own (connection caps, header and idle timeouts), Host,
  Origin, Content-Type and token checks, one-line JSON refusals.

Endpoints (JSON):
- `POST /annotate` {"client", "session", "model_fingerprint", "env_id", "renderer", "history_len",
  "layout", "tasks", "states": [{"mission", "history": [[obs, action], ...], "observation",
  "valid_actions", "visits"[, "frames", "prev_actions" for a hop state]}][, "wait": seconds]} ->
  202 {"queued", "queue", "landed"[, "failed", "failure", "pending"]} (`landed`: the trainer's states
  annotated since its previous request; `failed`: those the engine could not annotate, with the
  last reason; with `wait` (at most 120 s) the answer comes once none of the trainer's states is
  queued or in the engine, or the wait is over, or a newer request of the trainer waits: `pending`
  says which). No other field is read: one is refused. An empty `states` list withdraws the
  trainer's pending states. Refusals are {"error": one line} with 400 (bad JSON or fields), 401
  (token), 403 (Host or Origin), 408 (too slow), 409 (another model or setup, or a session with
  states queued or waiting from another peer), 413 (too large), 415 (not JSON), 429 (a client's or
  a peer's cap) or 503 (the server's), the last two with Retry-After (docs/commands/serve.md lists
  every limit).
- `GET /stats` -> the queue, the requests waiting, totals (states, rows, batches, refusals by kind,
  connections refused and evicted, failed states), throughput, the setup, the limits, the model,
  the cache and the resident memory.
"""

from __future__ import annotations

from illm_tools.annotate.wire import record_to_json  # noqa: F401  (the request format)
from illm_tools.serve.config import ServeConfig, ServeLimits, token_bits  # noqa: F401
from illm_tools.serve.http import serve  # noqa: F401
from illm_tools.serve.protocol import RequestError, ServerTerms  # noqa: F401
from illm_tools.serve.scheduler import AnnotationServer  # noqa: F401

MAX_REQUEST_BYTES = ServeLimits().max_request_bytes
"""The default largest request body (413 above; `--max-request-mb`)."""
