"""The HTTP side of `illm serve`: aiohttp's request handling behind a gate of our own.

The gate (`Gate`) owns the listening socket's connections, whatever aiohttp version runs: at most
`max_connections` open and `max_connections_per_peer` from one peer (loopback as one, an IPv4 /24,
an IPv6 /64: `config.peer_group`; a further one is answered 503 and closed, except that with every
connection taken an idle one is closed to make room, those that never passed a request's checks
first: strangers without the token cannot hold the server's connections); a connection that has
started a request's headers has `header_timeout` seconds to finish them, and one idle between
requests `request_timeout` seconds, then it is closed; a request's body has `request_timeout`
(408). aiohttp parses at most `MAX_HEADERS` headers and decompresses nothing: a body with a
`Content-Encoding` is answered 415 unread. Then, per request: the Host header must name the server's own address when it listens on
loopback without a token, and an Origin header must be the server's own origin (a web page in a
browser on the node cannot post to it: 403); a POST must be `Content-Type: application/json` (415);
the token, when there is one (401, the connection closed); the body is read within the timeout (a
Content-Length over the limit: 413 unread) and checked whole (`intake.Intake.take`), and a
request that waits for its states keeps its trainer's name only. A client that disconnects cancels
its request's handler (aiohttp's `handler_cancellation`): nothing is held for a client that has
gone. Every refusal is one line of JSON and at most one log line, never a traceback.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import time

from illm_tools.annotate.wire import TOKEN_ENV
from illm_tools.serve.config import peer_group
from illm_tools.serve.protocol import RequestError
from illm_tools.serve.scheduler import AnnotationServer

log = logging.getLogger(__name__)

MAX_HEADERS = 64
"""Headers aiohttp parses in one request (more: 400); a trainer sends six."""

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


class _Connection(asyncio.Protocol):
    """One connection: aiohttp's request handler inside, counted and timed by the gate."""

    def __init__(self, gate: Gate):
        self.gate, self.inner, self.transport, self.peer = gate, None, None, ""
        self.active = 0  # requests being handled now
        self.since = time.monotonic()  # when it last started being idle (or opened)
        self.started: float | None = None  # when the bytes of a request not yet handled began to arrive
        self.proven = False  # a request of its own passed the checks (the token, where one is set)

    def connection_made(self, transport) -> None:
        self.transport = transport
        peer = transport.get_extra_info("peername")
        self.peer = peer_group(str(peer[0]) if isinstance(peer, tuple) else str(peer))
        refusal = self.gate.admit(self)
        if refusal is not None:
            self.gate.server.totals["connections_refused"] += 1
            body = json.dumps({"error": refusal}).encode()
            transport.write(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\nRetry-After: 5\r\n"
                            b"Connection: close\r\nContent-Length: %d\r\n\r\n%s" % (len(body), body))
            transport.close()
            return
        self.inner = self.gate.factory()
        self.inner.connection_made(transport)

    def connection_lost(self, exc) -> None:
        self.gate.release(self)
        if self.inner is not None:
            self.inner.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if not self.active and self.started is None:
            self.started = time.monotonic()  # a request's headers begin: `header_timeout` to finish them
        if self.inner is not None:
            self.inner.data_received(data)

    def eof_received(self):
        return self.inner.eof_received() if self.inner is not None else None

    def pause_writing(self) -> None:
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()


class Gate:
    """The connections of a server: caps in all and per peer, and the idle and header timeout."""

    def __init__(self, server: AnnotationServer, factory, timeout: float):
        self.server, self.factory, self.timeout = server, factory, timeout
        self.header_timeout = min(server.limits.header_timeout, timeout)
        self.limits = server.limits
        self.open: dict[int, _Connection] = {}  # id(transport) -> connection
        self.per_peer: dict[str, int] = {}

    def admit(self, conn: _Connection) -> str | None:
        """None when the connection may stay, else the one-line reason it is refused. With every
        connection taken, an idle one makes room (`evictable`) before a new one is refused."""
        if self.per_peer.get(conn.peer, 0) >= self.limits.max_connections_per_peer:
            return (f"this peer ({conn.peer}) has {self.per_peer[conn.peer]} connections open, the server's "
                    "--max-connections-per-peer: close some")
        if len(self.open) >= self.limits.max_connections:
            idle = self.evictable()
            if idle is None:
                return f"the server has {len(self.open)} connections open, its --max-connections: try again shortly"
            idle.transport.close()
            self.release(idle)
            self.server.totals["connections_evicted"] += 1
        self.open[id(conn.transport)] = conn
        self.per_peer[conn.peer] = self.per_peer.get(conn.peer, 0) + 1
        self.server.connections = len(self.open)
        return None

    def evictable(self) -> _Connection | None:
        """The connection closed to make room for a new one: none in a request; of the others, those
        that never passed a request's checks (the token) first, each kind longest idle first."""
        idle = [c for c in self.open.values() if not c.active and c.transport is not None]
        return min(idle, key=lambda c: (c.proven, c.since), default=None)

    def release(self, conn: _Connection) -> None:
        if self.open.pop(id(conn.transport), None) is not None:
            left = self.per_peer.get(conn.peer, 1) - 1
            if left > 0:
                self.per_peer[conn.peer] = left
            else:
                self.per_peer.pop(conn.peer, None)
            self.server.connections = len(self.open)

    def of(self, transport) -> _Connection | None:
        return self.open.get(id(transport))

    async def sweep(self) -> None:
        """Close, every fraction of the timeouts, the connections idle longer than the request timeout,
        or stuck in a request's headers longer than the header timeout."""
        while True:
            await asyncio.sleep(min(1.0, self.header_timeout / 4))
            now = time.monotonic()
            for conn in list(self.open.values()):
                stuck = conn.started is not None and now - conn.started > self.header_timeout
                if not conn.active and (stuck or now - conn.since > self.timeout) and conn.transport is not None:
                    conn.transport.close()
                    self.release(conn)


def make_app(server: AnnotationServer, *, token: str | None = None, request_timeout: float = 30.0,
             own_hosts: tuple[str, ...] | None = None, gate: Gate | None = None):
    """The aiohttp application of a server: POST /annotate, GET /stats. `token`: every request must
    carry it (`Authorization: Bearer TOKEN`, compared in constant time); `own_hosts`: the Host values
    accepted ("host:port"), None for any; `gate`: marks its connections busy while a request runs."""
    from aiohttp import web

    kinds = {503: "busy", 429: "throttled", 408: "timeouts", 401: "unauthorized", 403: "forbidden"}

    def error(status: int, message: str, retry_after: int | None = None, close: bool = False) -> web.Response:
        server.totals[kinds.get(status, "refused")] += 1
        headers = {"Retry-After": str(retry_after)} if retry_after is not None else None
        response = web.json_response({"error": message}, status=status, headers=headers)
        if close:
            response.force_close()
        return response

    expected = token.encode() if token else None
    own_origins = None if own_hosts is None else {f"http://{h}" for h in own_hosts}

    def refusal(request: web.Request) -> web.Response | None:
        if own_hosts is not None and request.headers.get("Host", "") not in own_hosts:
            return error(403, f"the Host header names another server than this one ({', '.join(own_hosts[:2])}): "
                              "send requests to the server's own address", close=True)
        origin = request.headers.get("Origin")
        if origin is not None and (own_origins is None or origin not in own_origins):
            return error(403, "cross-origin requests are refused: a trainer sends no Origin header", close=True)
        encoding = request.headers.get("Content-Encoding", "identity").strip().lower()
        if encoding not in ("", "identity"):  # never decompressed (a small body can inflate without bound)
            return error(415, f"a request's body must not be compressed (Content-Encoding {encoding[:40]!r})", close=True)
        if request.method == "POST" and request.content_type != "application/json":
            return error(415, f"a request's Content-Type must be application/json, got {request.content_type[:60]!r}",
                         close=True)
        if expected is not None:
            scheme, _, given = request.headers.get("Authorization", "").partition(" ")
            given_bytes = given.strip().encode(errors="surrogateescape")  # as sent, whatever its bytes
            if scheme.lower() != "bearer" or not hmac.compare_digest(given_bytes, expected):
                what = "a wrong token" if given else "no token"
                response = error(401, f"this server needs its token and the request has {what}: pass the server's "
                                      f"token with --annotator-token, or set {TOKEN_ENV}", close=True)
                response.headers["WWW-Authenticate"] = 'Bearer realm="illm serve"'
                return response  # its body unread: the connection is closed
        return None

    @web.middleware
    async def access(request: web.Request, handler):
        conn = gate.of(request.transport) if gate is not None else None
        if conn is not None:
            conn.active += 1
            conn.started = None
        try:
            refused = refusal(request)
            if refused is not None:
                return refused
            if conn is not None:
                conn.proven = True
            return await handler(request)
        except web.HTTPException:
            raise
        except Exception as e:  # noqa: BLE001 - a bug here answers one line and logs one, never a traceback
            log.warning("a request to %s failed: %s: %s", request.path, type(e).__name__, str(e)[:200])
            return error(500, f"the server failed on this request ({type(e).__name__}); it goes on")
        finally:
            if conn is not None:
                conn.active -= 1
                conn.since = time.monotonic()

    async def annotate(request: web.Request) -> web.Response:
        taken = await take(request)
        if isinstance(taken, web.Response):
            return taken
        answer, trainer, wait = taken  # all that is kept of the request while it waits
        if wait and answer["queued"]:  # held until its states land (a trainer in --live-mode sync)
            later = await server.settled(trainer, wait, peer_group(request.remote or ""))
            answer = {**answer, **later, "landed": answer["landed"] + later["landed"],
                      "failed": answer.get("failed", 0) + later.get("failed", 0)}
            if not answer["failed"]:
                answer.pop("failed")
        return web.json_response(answer, status=202)

    async def take(request: web.Request):
        """The request read, checked and queued (`Intake.take`): (answer, trainer, wait), or the
        refusal. Its body lives in no variable here, so nothing of it outlasts its check."""
        limit = server.limits.max_request_bytes
        try:
            return await server.intake.take(await asyncio.wait_for(read_body(request, limit), request_timeout),
                                            peer_group(request.remote or ""))
        except TooLarge:
            return error(413, f"the request is larger than the server's --max-request-mb "
                              f"{server.limits.max_request_mb:g}: send fewer states", close=True)
        except asyncio.TimeoutError:  # a slow or stalled client: cut off, so it holds nothing
            return error(408, f"the request was not sent whole within {request_timeout:g} s", close=True)
        except RequestError as e:
            log.info("refused a request (%d): %s", e.status, str(e)[:300])
            return error(e.status, str(e), e.retry_after)
        except (ConnectionError, asyncio.IncompleteReadError, OSError):  # the client went away mid-request
            return web.Response(status=400)

    async def stats(request: web.Request) -> web.Response:
        return web.json_response(server.stats())

    app = web.Application(client_max_size=server.limits.max_request_bytes, middlewares=[access])
    app.router.add_post("/annotate", annotate)
    app.router.add_get("/stats", stats)
    return app


class TooLarge(Exception):
    """A request body beyond the server's --max-request-mb."""


async def read_body(request, limit: int) -> bytearray:
    """A request's body, at most `limit` bytes (TooLarge beyond: a Content-Length over it before any
    byte is read). Read here rather than by `request.read()`, which keeps the bytes on the request for
    as long as the request lives (a waiting request would hold them)."""
    if request.content_length is not None and request.content_length > limit:
        raise TooLarge
    body = bytearray()
    while chunk := await request.content.readany():
        if len(body) + len(chunk) > limit:
            raise TooLarge
        body += chunk
    return body


def own_hosts(host: str, port: int, token: str | None) -> tuple[str, ...] | None:
    """The Host header values a server answers: on loopback without a token, its own address under
    the names of loopback; otherwise any (the token keeps strangers out, and the names a cluster
    reaches the node by are not known here)."""
    from illm_tools.serve.config import is_loopback

    if token is not None or not is_loopback(host):
        return None
    names = {host if ":" not in host else f"[{host}]", *LOOPBACK_NAMES}
    return tuple(f"{name}:{port}" for name in sorted(names))


async def serve(server: AnnotationServer, host: str, port: int, stop: asyncio.Event, on_ready=None, *,
                token: str | None = None, request_timeout: float | None = None) -> None:
    """Serve until `stop` is set, then finish the batch in progress (its shard written whole) within
    its deadline. `token`: required on every request; `request_timeout` (default the server's
    limit): seconds a client has for its headers, then its body, and an idle connection stays open."""
    from aiohttp import web

    timeout = request_timeout if request_timeout is not None else server.limits.request_timeout
    loop = asyncio.get_running_loop()
    gate = Gate(server, None, timeout)
    listening = await loop.create_server(lambda: _Connection(gate), host, port, start_serving=False)
    bound = listening.sockets[0].getsockname()[1]
    app = make_app(server, token=token, request_timeout=timeout, own_hosts=own_hosts(host, bound, token), gate=gate)
    # the gate closes idle and stalled connections (`Gate.sweep`), whatever this aiohttp version does itself
    # handler_cancellation: a client gone cancels its request's handler (aiohttp's documented way), so a
    # request waiting for its states (`settled`) or for its check holds nothing once its client has left
    runner = web.AppRunner(app, access_log=None, handle_signals=False, keepalive_timeout=3600,
                           auto_decompress=False, max_headers=MAX_HEADERS, handler_cancellation=True)
    await runner.setup()
    gate.factory = runner.server
    await listening.start_serving()
    sweeper = asyncio.ensure_future(gate.sweep())
    if on_ready is not None:
        on_ready([s.getsockname()[:2] for s in listening.sockets])
    try:
        await server.run(stop)
    finally:
        sweeper.cancel()
        listening.close()
        await runner.cleanup()
