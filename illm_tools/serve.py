"""`illm serve`: one loaded LLM answering the live-annotation requests of many `illm train` runs.

A trainer started with `--annotator http://HOST:PORT` posts, after each rollout, the states its
cache lookup missed (most visited first, with their visit counts) instead of handing them to a
worker of its own; the server annotates them through the same `Annotator` and cache API as
`illm annotate` and the trainer's own worker, so the answers land in the shared cache, where the
trainer finds them on a later rollout (as with its own asynchronous worker: the trainer never
waits). One model in memory serves every trainer.

Scheduling. Each trainer has one pending list, replaced by its newest request (its priorities move
as its run goes on, as the local worker keeps only the newest list). A trainer is named by `client`
(its run) and `session` (a random id it makes when it starts): the list belongs to the pair, so no
other trainer (a stranger using the same client name, a resumed copy of the run) can replace or
withdraw it. A batch takes `chunk` states across all trainers, highest visit count first; a state
two trainers both missed (same keys) is annotated once, with their visits summed. Each batch is
written as one shard through the cache's locked manifest, whole or not at all.

Access and limits (`ServeConfig`). With a token, every request must carry `Authorization: Bearer
TOKEN` (compared in constant time; 401 and one line without it); without one the server listens on
loopback only. A request carries at most `max_states` states (413), the server queues states of at
most `max_clients` trainers and `max_queue` states in all: a request beyond either gets 503 with
`Retry-After` (seconds), and the trainer backs off and goes on training. A client has
`request_timeout` seconds to send its request (408 after, the connection closed), and an idle
connection is closed after as long, so a slow or stalled client holds no worker. Stopping (Ctrl-C,
SIGTERM) finishes the batch in progress and writes it; requests meanwhile get 503 (their trainers
send them again to the next server).

The HTTP side is aiohttp's server (an asyncio server from the package registry; the standard
library's `http.server` handles one request at a time per thread and has no request size limit,
body timeouts or graceful shutdown). The model runs in one executor thread, so requests and
`/stats` are answered while a batch is being annotated.

Endpoints (JSON):
- `POST /annotate` {"client", "session", "model_fingerprint", "env_id", "renderer", "history_len",
  "layout", "tasks", "states": [{"mission", "history": [[obs, action], ...], "observation",
  "valid_actions", "visits"[, "frames", "prev_actions" for a hop state]}]} -> 202 {"queued",
  "queue", "landed"} (`landed`: the trainer's states annotated since its previous request). An
  empty `states` list withdraws the trainer's pending states. Refused requests get a 4xx or 503
  status and {"error": one line}: 400 bad JSON or fields, 401 no or a wrong token, 408 sent too
  slowly, 409 a model fingerprint that is not the server's (the keys would never meet), 413 too
  large (bytes or states), 503 the queue or the trainer count is full, or the server is stopping.
- `GET /stats` -> the queue (states waiting, states being annotated now, trainers), totals (states
  annotated, rows written, batches, requests, refusals by kind), throughput (states/s over the
  annotating time and since start), the limits, the model and cache, and the server's resident
  memory (after each batch the freed memory is handed back to the system: `release_free_memory`).
A client that disconnects mid-request leaves nothing behind: a request is queued only once it
has been read and checked whole. A hop state (iLLM(hop)) also carries its observation window:
each raw observation as shape, dtype and base64 bytes, and each step's previous action; the
server checks them against the content names the state's keys are made of.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from illm_tools.annotate.wire import PROTOCOL, TOKEN_ENV, check_token
from illm_tools.annotate.wire import record_to_json  # noqa: F401  (the request format: re-exported)
from illm_tools.errors import UsageError
from illm_tools.llm.spec import LLMSpec
from illm_tools.tasks.setup import AnnotationSetup
from illm_tools.tasks.state import StateRecord

log = logging.getLogger(__name__)

MAX_REQUEST_BYTES = 16 * 1024 * 1024
"""Largest request body accepted (413 above): thousands of states with 3-step histories."""
MAX_RETRY_AFTER = 60
"""Longest Retry-After a busy server answers (seconds)."""


class RequestError(ValueError):
    """A request the server refuses: its HTTP status and one line (503: with Retry-After seconds)."""

    def __init__(self, status: int, message: str, retry_after: int | None = None):
        super().__init__(message)
        self.status = status
        self.retry_after = retry_after


def is_loopback(host: str) -> bool:
    """Whether listening on `host` keeps the server on this machine: a loopback address (127.0.0.0/8,
    ::1) or a name that resolves only to loopback addresses ("localhost"); "" (every address) is not."""
    import ipaddress
    import socket

    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    if not host:
        return False
    try:
        found = {info[4][0].split("%")[0] for info in socket.getaddrinfo(host, None)}
    except OSError:
        return False
    return bool(found) and all(ipaddress.ip_address(a).is_loopback for a in found)


def release_free_memory() -> None:
    """Hand the memory a batch freed back to the system: glibc keeps freed blocks in its per-thread
    arenas, and a server that runs for days would otherwise creep up in resident size as batches of
    other shapes leave them fragmented. A no-op where the C library is not glibc."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def resident_mb() -> float | None:
    """This process's resident memory in MB (Linux's /proc; None elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


@dataclass
class ServeConfig:
    """An `illm serve` server: the cache it writes, the LLM it loads, where it listens, how it batches."""

    cache: Path = Path("data/ann")
    """Annotation cache the answers go to (the trainers' --cache)."""
    llm: LLMSpec = field(default_factory=LLMSpec)
    """The LLM that answers; none of its options given: the cache's one model setup (`adopt_model`)."""
    port: int = 8765
    """TCP port (0: any free one, printed when ready)."""
    host: str = "127.0.0.1"
    """Address to listen on: loopback by default; any other (0.0.0.0, this machine's cluster address)
    needs a token."""
    token: str | None = field(default=None, repr=False)
    """Token every request must carry (401 without it; trainers pass it with --annotator-token), at
    least 16 characters; default: the ILLM_SERVE_TOKEN environment variable, which keeps it out of
    `ps` and the shell's history. Required to listen beyond loopback. Never printed or logged."""
    batch_size: int = 8
    """States per LLM batch."""
    chunk: int = 16
    """States taken per round across all trainers (highest visit counts first), written as one shard."""
    threads: int = 0
    """Torch threads of the model; 0: every core."""
    max_clients: int = 64
    """Trainers whose states are queued at once; a further one gets 503 with Retry-After until a list drains."""
    max_states: int = 1024
    """States in one request (413 above; a trainer sends at most this many per rollout)."""
    max_queue: int = 8192
    """States queued across all trainers; a request that would go beyond gets 503 with Retry-After
    (the trainer backs off and goes on training)."""
    request_timeout: float = 30.0
    """Seconds a client has to send a request (408 after), and an idle connection stays open: a
    slow or stalled client holds no worker."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers

        self.cache = Path(self.cache)
        check_numbers(self, positive=("batch_size", "chunk", "max_clients", "max_states", "max_queue",
                                      "request_timeout"), non_negative=("threads", "port"))
        if self.port >= 65536:
            raise UsageError(f"--port must be in 0..65535, got {self.port}")
        if self.token is None:
            self.token = os.environ.get(TOKEN_ENV) or None
        if self.token is not None:
            check_token(self.token, "--token")
        elif not is_loopback(self.host):
            raise UsageError(f"--host {self.host or '(every address)'} listens beyond this machine, where anyone could "
                             f"send states: give the server a token (--token, or the {TOKEN_ENV} environment variable) "
                             "and pass it to every trainer (--annotator-token, or the same variable)")
        check_folder(self.cache, "--cache")


@dataclass
class Pending:
    """One state waiting, with the clients that asked for it and their summed visits."""

    setup: AnnotationSetup
    record: StateRecord
    visits: int
    clients: set[str] = field(default_factory=set)


def _hop_record(record: StateRecord, item: dict) -> StateRecord:
    """The hop state of a request entry: its window decoded, and checked against the content names
    its keys are made of (each step's name is the digest of its observation and previous action),
    so a window that does not match its names never reaches the cache."""
    from illm_tools.hop.context import HopRecord, step_name

    frames, prev = item.get("frames"), item.get("prev_actions")
    n = len(record.history) + 1
    if not isinstance(frames, list) or not isinstance(prev, list) or len(frames) != n or len(prev) != n:
        raise RequestError(400, f"a hop state needs frames and prev_actions for its {n} window steps")
    raws = []
    for f in frames:
        try:
            raw = np.frombuffer(base64.b64decode(f["data"], validate=True), dtype=np.dtype(f["dtype"]))
            raws.append(raw.reshape([int(d) for d in f["shape"]]))
        except (KeyError, TypeError, ValueError, binascii.Error) as e:
            raise RequestError(400, f"a hop frame is not {{shape, dtype, base64 data}} ({e})") from None
    actions = record.valid_actions
    if not all(isinstance(a, int) and not isinstance(a, bool) and -1 <= a < len(actions) for a in prev):
        raise RequestError(400, f"prev_actions must be action indices in -1..{len(actions) - 1}")
    names = [name for name, _ in record.history] + [record.observation]
    for j, (raw, a, name) in enumerate(zip(raws, prev, names)):
        if step_name(raw, actions[a] if a >= 0 else None) != name:
            raise RequestError(400, f"hop window step {j} does not match its content name: the frames or "
                                    "previous actions are not the state's")
        if j and record.history[j - 1][1] != actions[a]:
            raise RequestError(400, f"hop window step {j}: its previous action is not the history's action")
    return HopRecord(record.mission, record.history, record.observation, record.valid_actions,
                     frames=tuple(raws), prev_actions=tuple(prev))


def _text(value, name: str) -> str:
    if not isinstance(value, str):
        raise RequestError(400, f"{name} must be a string, got {type(value).__name__}")
    return value


def parse_state(item, hop: bool = False) -> tuple[StateRecord, int]:
    """(record, visits) of one entry of `states` (`hop`: with its observation window, a
    `HopRecord`); RequestError(400) naming what is wrong."""
    if not isinstance(item, dict):
        raise RequestError(400, "each state must be an object with mission, history, observation, valid_actions")
    missing = [k for k in ("mission", "history", "observation", "valid_actions") if k not in item]
    if missing:
        raise RequestError(400, f"a state lacks {', '.join(missing)}")
    history = item["history"]
    if not isinstance(history, list) or not all(isinstance(p, list) and len(p) == 2 for p in history):
        raise RequestError(400, "history must be a list of [observation, action] pairs")
    actions = item["valid_actions"]
    if not isinstance(actions, list) or not actions:
        raise RequestError(400, "valid_actions must be a non-empty list of strings")
    visits = item.get("visits", 1)
    if not isinstance(visits, int) or isinstance(visits, bool) or visits < 0:
        raise RequestError(400, f"visits must be a whole number >= 0, got {visits!r}")
    record = StateRecord(_text(item["mission"], "mission"),
                         tuple((_text(o, "a history observation"), _text(a, "a history action")) for o, a in history),
                         _text(item["observation"], "observation"),
                         tuple(_text(a, "a valid action") for a in actions))
    return (_hop_record(record, item) if hop else record), visits


class AnnotationServer:
    """The queue, the scheduler and the model behind `illm serve` (the HTTP layer is `make_app`)."""

    def __init__(self, lm, cache, *, llm: LLMSpec, batch_size: int = ServeConfig.batch_size,
                 chunk: int = ServeConfig.chunk, max_clients: int = ServeConfig.max_clients,
                 max_states: int = ServeConfig.max_states, max_queue: int = ServeConfig.max_queue):
        from illm_tools.keys import fingerprint_hash
        from illm_tools.llm.backend import as_backend

        self.lm = as_backend(lm)
        self.cache = cache
        self.llm = llm
        """The model as it was loaded (placed: its device and dtype resolved)."""
        self.model = llm.model
        self.batch_size, self.chunk = batch_size, chunk
        self.max_clients, self.max_states, self.max_queue = max_clients, max_states, max_queue
        self.annotating = 0
        """States in the batch being annotated now (0: idle)."""
        self.fingerprint = fingerprint_hash(self.lm.fingerprint)
        self._annotators: dict[tuple, object] = {}
        # (client, session) -> (setup, record) -> its pending entry: a trainer's list, its own only
        self._clients: dict[tuple[str, str], dict[tuple, Pending]] = {}
        self._landed: dict[tuple[str, str], int] = {}
        self._seen: dict[tuple[str, str], float] = {}  # when each trainer last sent (to forget the gone)
        self._wake = asyncio.Event()
        self._stop: asyncio.Event | None = None
        self.started = time.time()
        self.totals = {"states": 0, "rows": 0, "batches": 0, "requests": 0, "refused": 0, "busy": 0,
                       "unauthorized": 0, "timeouts": 0, "seconds": 0.0, "errors": 0}
        self.last_error: str | None = None

    @property
    def stopping(self) -> bool:
        """Whether a stop was asked: the batch in progress is finished, nothing more is queued."""
        return self._stop is not None and self._stop.is_set()

    def retry_after(self) -> int:
        """Seconds a refused trainer should wait: about one batch's time at the throughput so far."""
        rate = self.totals["states"] / self.totals["seconds"] if self.totals["seconds"] else 0.0
        return min(MAX_RETRY_AFTER, max(1, math.ceil(self.chunk / rate))) if rate else 5

    # --- requests ------------------------------------------------------------------------------
    def submit(self, body) -> dict:
        """Queue a parsed request body for its trainer (replacing that trainer's pending list)."""
        if not isinstance(body, dict):
            raise RequestError(400, "the request body must be a JSON object")
        missing = [k for k in ("client", "session", "model_fingerprint", "states") if k not in body]
        if missing:
            raise RequestError(400, f"the request lacks {', '.join(missing)} (a trainer of protocol {PROTOCOL} "
                                    "sends them: use the server's illm version)")
        trainer = (_text(body["client"], "client"), _text(body["session"], "session"))
        if body["model_fingerprint"] != self.fingerprint:
            raise RequestError(409, f"this server annotates with {self.llm.options()} (fingerprint {self.fingerprint}); "
                                    f"the request's fingerprint {body['model_fingerprint']!r} is another model setup: "
                                    "train with the server's --model, --dtype and --quant, or start a server for yours")
        try:
            setup = AnnotationSetup.from_wire(body)
        except UsageError as e:  # any bad setup field is the client's error
            raise RequestError(400, str(e)) from None
        if not isinstance(body["states"], list):
            raise RequestError(400, "states must be a list")
        if len(body["states"]) > self.max_states:
            raise RequestError(413, f"a request carries at most {self.max_states:,} states (the server's --max-states), "
                                    f"this one {len(body['states']):,}: send the most visited first")
        if self.stopping:
            raise RequestError(503, "the server is stopping: send the states again when it is back",
                               self.retry_after())
        hop, history_len = setup.hop, setup.history_len
        entries = {}
        for item in body["states"]:
            record, visits = parse_state(item, hop)
            if len(record.history) > history_len:
                raise RequestError(400, f"a state has {len(record.history)} history steps, more than history_len "
                                        f"{history_len}")
            entry = entries.setdefault((setup, record), Pending(setup, record, 0, {trainer}))
            entry.visits += visits
        if entries:
            self._check_room(trainer, entries)
        self.totals["requests"] += 1
        self._seen[trainer] = time.monotonic()
        if entries:
            self._clients[trainer] = entries
            self._wake.set()
        else:  # withdrawn: the trainer is done
            self._clients.pop(trainer, None)
            self._seen.pop(trainer, None)
        self._forget_gone()
        landed = self._landed.pop(trainer, 0)
        return {"queued": len(entries), "queue": self.queue_size(), "landed": landed}

    def _check_room(self, trainer: tuple[str, str], entries: dict) -> None:
        """RequestError(503) when queueing `entries` for `trainer` (in place of its list) would go
        beyond the trainer or state limits; the trainer's current list stays queued."""
        if trainer not in self._clients and len(self._clients) >= self.max_clients:
            raise RequestError(503, f"the server queues the states of {len(self._clients)} trainers, its limit "
                                    "(--max-clients): this run backs off and sends them again", self.retry_after())
        others = {k for who, pending in self._clients.items() if who != trainer for k in pending}
        total = len(others | entries.keys())
        if total > self.max_queue:
            raise RequestError(503, f"the queue would hold {total:,} states, beyond the server's --max-queue "
                                    f"{self.max_queue:,}: this run backs off and sends them again", self.retry_after())

    def _forget_gone(self) -> None:
        """Drop what is kept of trainers that went away without withdrawing (their landed counts)
        once there are many: those with no pending list, longest unseen first."""
        if len(self._seen) <= 4 * self.max_clients:
            return
        idle = sorted((t, who) for who, t in self._seen.items() if who not in self._clients)
        for _, who in idle[: len(self._seen) - 2 * self.max_clients]:
            self._seen.pop(who, None)
            self._landed.pop(who, None)

    def queue_size(self) -> int:
        return len({k for entries in self._clients.values() for k in entries})

    def stats(self) -> dict:
        """The queue, totals and throughput (GET /stats)."""
        busy = self.totals["seconds"]
        up = time.time() - self.started
        return {"protocol": PROTOCOL, "model": self.model, "model_options": self.llm.options(),
                "model_fingerprint": self.fingerprint, "cache": str(self.cache.root), "queue": self.queue_size(),
                "annotating": self.annotating, "clients": len(self._clients),
                "annotated_states": self.totals["states"], "rows": self.totals["rows"],
                "batches": self.totals["batches"], "requests": self.totals["requests"],
                "refused": self.totals["refused"], "busy": self.totals["busy"],
                "unauthorized": self.totals["unauthorized"], "timeouts": self.totals["timeouts"],
                "errors": self.totals["errors"], "last_error": self.last_error, "stopping": self.stopping,
                "limits": {"max_clients": self.max_clients, "max_states": self.max_states,
                           "max_queue": self.max_queue},
                "states_per_s": self.totals["states"] / busy if busy else 0.0,
                "states_per_s_since_start": self.totals["states"] / up if up else 0.0, "uptime_s": up,
                "resident_mb": resident_mb()}

    # --- the scheduler ---------------------------------------------------------------------------
    def next_batch(self) -> list[Pending]:
        """Take up to `chunk` pending states across clients, highest summed visits first; a state
        asked by several clients is one entry with their visits summed."""
        merged: dict[tuple, Pending] = {}
        for entries in self._clients.values():
            for key, entry in entries.items():
                into = merged.get(key)
                if into is None:
                    merged[key] = Pending(entry.setup, entry.record, entry.visits, set(entry.clients))
                else:
                    into.visits += entry.visits
                    into.clients |= entry.clients
        batch = sorted(merged.values(), key=lambda p: -p.visits)[: self.chunk]  # stable: ties in arrival order
        taken = {(p.setup, p.record) for p in batch}
        for client in list(self._clients):
            entries = self._clients[client]
            for key in taken & entries.keys():
                del entries[key]
            if not entries:
                del self._clients[client]
        return batch

    def annotator(self, setup: AnnotationSetup):
        from illm_tools.annotate.engine import Annotator

        key = (setup.history_len, setup.layout, setup.tasks)
        if key not in self._annotators:
            self._annotators[key] = Annotator.of_setup(self.lm, self.cache, self.llm, setup,
                                                       batch_size=self.batch_size, chunk=self.chunk)
        return self._annotators[key]

    def annotate(self, batch: Sequence[Pending]) -> tuple[int, int]:
        """Annotate a batch (blocking; runs in the executor thread, touching no queue state): what
        the cache lacks of it, one shard per setup; returns (states annotated, rows written)."""
        self.cache.refresh()  # trainers and other servers may have written meanwhile
        done = rows = 0
        by_setup: dict[AnnotationSetup, list[Pending]] = {}
        for p in batch:
            by_setup.setdefault(p.setup, []).append(p)
        for setup, items in by_setup.items():
            stats = self.annotator(setup).annotate_states([p.record for p in items], setup.env_id, setup.renderer)
            done, rows = done + stats.annotated_states, rows + stats.rows
        release_free_memory()
        return done, rows

    async def run(self, stop: asyncio.Event) -> None:
        """Annotate batches until `stop` is set; the batch in progress is finished first (and
        requests meanwhile are refused with 503: `stopping`)."""
        loop = asyncio.get_running_loop()
        self._stop = stop
        while not stop.is_set():
            batch = self.next_batch()
            if not batch:
                self._wake.clear()
                waiter = asyncio.ensure_future(self._wake.wait())
                stopper = asyncio.ensure_future(stop.wait())
                await asyncio.wait([waiter, stopper], return_when=asyncio.FIRST_COMPLETED)
                waiter.cancel()
                stopper.cancel()
                continue
            start = time.perf_counter()
            self.annotating = len(batch)
            try:
                done = await loop.run_in_executor(None, self.annotate, batch)
            except Exception as e:  # noqa: BLE001 - one bad batch must not stop the server
                self.totals["errors"] += 1
                self.last_error = f"{type(e).__name__}: {e}"
                log.warning("a batch of %d states failed (%s); the server goes on", len(batch), self.last_error)
                continue
            finally:
                self.annotating = 0
            self.totals["seconds"] += time.perf_counter() - start
            self.totals["states"] += done[0]
            self.totals["rows"] += done[1]
            self.totals["batches"] += 1
            for p in batch:  # in the cache now (annotated, or already there): landed for each asker still here
                for trainer in p.clients & self._seen.keys():
                    self._landed[trainer] = self._landed.get(trainer, 0) + 1


def make_app(server: AnnotationServer, *, token: str | None = None,
             request_timeout: float = ServeConfig.request_timeout):
    """The aiohttp application of a server: POST /annotate, GET /stats; with `token`, every request
    must carry it (`Authorization: Bearer TOKEN`, compared in constant time)."""
    import hmac
    import json

    from aiohttp import web

    def error(status: int, message: str, retry_after: int | None = None) -> web.Response:
        server.totals["busy" if status == 503 else "timeouts" if status == 408 else "refused"] += 1
        headers = {"Retry-After": str(retry_after)} if retry_after is not None else None
        return web.json_response({"error": message}, status=status, headers=headers)

    expected = token.encode() if token else None

    @web.middleware
    async def access(request: web.Request, handler):
        if expected is not None:
            scheme, _, given = request.headers.get("Authorization", "").partition(" ")
            given_bytes = given.strip().encode(errors="surrogateescape")  # as sent, whatever its bytes
            if scheme.lower() != "bearer" or not hmac.compare_digest(given_bytes, expected):
                server.totals["unauthorized"] += 1
                what = "a wrong token" if given else "no token"
                response = web.json_response(
                    {"error": f"this server needs its token and the request has {what}: pass the server's token "
                              f"with --annotator-token, or set {TOKEN_ENV}"},
                    status=401, headers={"WWW-Authenticate": 'Bearer realm="illm serve"'})
                if request.can_read_body:  # do not read a stranger's body: close the connection instead
                    response.force_close()
                return response
        return await handler(request)

    async def annotate(request: web.Request) -> web.Response:
        try:
            raw = await asyncio.wait_for(request.read(), request_timeout)
        except web.HTTPRequestEntityTooLarge:
            return error(413, f"the request is larger than {MAX_REQUEST_BYTES // 2**20} MiB: send fewer states")
        except asyncio.TimeoutError:  # a slow or stalled client: cut off, so it holds nothing
            response = error(408, f"the request was not sent whole within {request_timeout:g} s")
            response.force_close()
            return response
        except (ConnectionError, asyncio.IncompleteReadError, OSError):  # the client went away mid-request
            return web.Response(status=400)
        try:
            body = json.loads(raw)
        except ValueError as e:
            return error(400, f"the request body is not JSON ({e})")
        try:
            answer = server.submit(body)
        except RequestError as e:
            return error(e.status, str(e), e.retry_after)
        return web.json_response(answer, status=202)

    async def stats(request: web.Request) -> web.Response:
        return web.json_response(server.stats())

    app = web.Application(client_max_size=MAX_REQUEST_BYTES, middlewares=[access])
    app.router.add_post("/annotate", annotate)
    app.router.add_get("/stats", stats)
    return app


async def serve(server: AnnotationServer, host: str, port: int, stop: asyncio.Event, on_ready=None, *,
                token: str | None = None, request_timeout: float = ServeConfig.request_timeout) -> None:
    """Serve until `stop` is set, then finish the batch in progress (its shard is written whole).
    `token`: required on every request; `request_timeout`: seconds a client has to send a request,
    and an idle connection stays open."""
    from aiohttp import web

    runner = web.AppRunner(make_app(server, token=token, request_timeout=request_timeout), access_log=None,
                           handle_signals=False, keepalive_timeout=request_timeout)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    if on_ready is not None:
        on_ready(runner.addresses)
    try:
        await server.run(stop)
    finally:
        await runner.cleanup()
