"""Live annotation by an `illm serve` server shared with other runs (`illm train --annotator URL`):
`RemoteLive`, the trainer's client, and `AnnotatorAccess`, the token it proves itself with. The
live annotators of the trainer's own machine (`sync`, `async`) are in `illm_tools.rl.live`; all
three take the same calls (`submit`, `landed`, `stats`, `close`) and log under that module's logger.
"""

from __future__ import annotations

import logging
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass

from illm_tools.llm.spec import LLMSpec
from illm_tools.web import NO_REDIRECTS
from illm_tools.tasks.annotation_setup import AnnotationSetup
from illm_tools.tasks.state import StateRecord

log = logging.getLogger("illm_tools.rl.live")
"""The live annotators' one logger (this client's lines are live annotation's, as `illm_tools.rl.live`'s are)."""


class BadAnswer(ValueError):
    """The server answered something that is not an illm server's answer (not a JSON object, too large)."""


MAX_ANSWER_BYTES = 1 << 20
"""The largest answer a trainer reads from its server (an answer is a few counts)."""
RETRY_AFTER = (1.0, 60.0)
"""The range a server's Retry-After is clamped to (seconds): no answer parks the sender longer."""
SYNC_WAIT = 60.0
"""Seconds a trainer in `--live-mode sync` lets the server hold a rollout's request until its states
land (the server's own cap is `illm_tools.serve.protocol.MAX_WAIT`)."""


@dataclass
class AnnotatorAccess:
    """How a trainer proves itself to its `illm serve` server. Not a field of TrainConfig: a run's
    settings are written to its folder (config.json, checkpoints), and a token must never be."""

    annotator_token: str | None = None
    """Token of the --annotator server (its --token); default: the ILLM_SERVE_TOKEN environment
    variable, which keeps it out of `ps` and the shell's history. Never written to the run's files."""


def answered_count(answer: dict, name: str, where: str) -> int:
    """A count the server answered (`landed`, `queued`, `failed`, a limit): absent is 0; anything but
    a whole number >= 0 is a `BadAnswer` (a hostile or broken server never raises in the trainer)."""
    value = answer.get(name, 0)
    if type(value) is not int or value < 0:
        raise BadAnswer(f"{where} answered {name} {str(value)[:40]!r}, not a count")
    return value


def retry_after(value) -> float:
    """A Retry-After header's seconds clamped to `RETRY_AFTER` (5 when absent or not a finite number)."""
    import math

    try:
        seconds = float(value) if value is not None else 5.0
    except ValueError:
        seconds = 5.0
    if not math.isfinite(seconds):
        seconds = RETRY_AFTER[1] if seconds > 0 else RETRY_AFTER[0]
    return min(RETRY_AFTER[1], max(RETRY_AFTER[0], seconds))


class RemoteLive:
    """Live annotation by an `illm serve` server (`illm train --annotator URL`): after each rollout
    the first `budget` missed states, with their visit counts, go to the server, which annotates
    them for every trainer it serves into the shared cache; a later rollout finds the answers there.

    `submit` only hands the list to a sender thread and returns: the trainer never waits on the
    network. The thread sends the newest list (a newer one replaces one not yet sent) with the
    standard library's `urllib` (one short JSON POST per rollout: no reason for another dependency
    on the trainer's side). The run is named at the server by `client` (its folder) and a random
    `session` made here, so its pending list is its own. `token` (default: the ILLM_SERVE_TOKEN
    environment variable) goes with every request.

    A server that cannot be reached, or refuses the token, when the run starts is refused in one
    line. Later, the run goes on training whatever the server does, and says each change once (not
    per rollout): a server that does not answer (down, restarting) is tried again after 1, 2, 4 ...
    `max_backoff` seconds, and the newest list is sent when it answers (what the dead server held
    is sent again: nothing is lost, and the cache's keys keep anything from being stored twice); a
    full server (503) is left alone for its Retry-After; a refused list (4xx) is dropped.

    With `wait` (seconds; `--live-mode sync`) there is no sender thread: `submit` posts the list and
    the server holds the answer until those states have landed (at most `wait` seconds), so this
    rollout uses them, as with an annotator of the trainer's own; a server that is down or busy is
    left alone for its back-off and the rollout goes on with what the cache has."""

    def __init__(self, url: str, *, client: str, llm: LLMSpec, setup: AnnotationSetup, budget: int | None,
                 token: str | None = None, timeout: float = 10.0, max_backoff: float = 10.0, wait: float = 0.0):
        import os
        import secrets
        import threading

        from illm_tools.annotate.wire import TOKEN_ENV

        self.url = url.rstrip("/")
        self.client, self.budget, self.timeout, self.max_backoff = client, budget, timeout, max_backoff
        self._token = token or os.environ.get(TOKEN_ENV) or None  # never logged
        self.session = secrets.token_hex(16)
        """This trainer's own id beside `client` (its run folder, which a resumed copy shares)."""
        self.setup = {**setup.wire(), "model_fingerprint": llm.fingerprint()}
        """The request's fields besides the client and the states (`AnnotationSetup.wire`)."""
        self.counts = {"sent": 0, "accepted": 0, "busy": 0, "refused": 0, "unanswered": 0}
        """Requests so far: sent, accepted (202), busy (503), refused (4xx), unanswered (no server)."""
        self._landed = 0
        self._queue = 0
        self._said = "up"  # what the log last said of the server: up, down, busy, refused
        info = self.server_stats(what="start")
        self._check_server(info, llm)
        self.max_states = self._max_states(info)
        self.wait = float(wait)
        self._lock = threading.Lock()
        self._outbox: list | None = None
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._failures, self._not_before = 0, 0.0  # the back-off of a server down or busy
        self._thread = None
        if not self.waits:
            self._thread = threading.Thread(target=self._sender, name="illm-annotator-client", daemon=True)
            self._thread.start()

    @property
    def waits(self) -> bool:
        """Whether `submit` returns once the server has put the states in the cache (sync)."""
        return self.wait > 0

    def _check_server(self, info: dict, llm: LLMSpec) -> None:
        from illm_tools.annotate.wire import PROTOCOL
        from illm_tools.errors import UsageError

        if info.get("protocol") != PROTOCOL:
            raise UsageError(f"the server at {self.url} speaks protocol {info.get('protocol')!r} and this trainer "
                             f"{PROTOCOL}: run the same illm version on both")
        if info.get("model_fingerprint") != self.setup["model_fingerprint"]:
            raise UsageError(f"the server at {self.url} annotates with {info.get('model_options') or info.get('model')}, "
                             f"another model setup than this run's {llm.options()}: its answers would never be this run's "
                             "targets; train with the server's options or start a server for this model")

    def _max_states(self, info: dict) -> int | None:
        """The states one request may carry, as the server's /stats says (None: no limit given);
        anything but a count is refused in one line."""
        from illm_tools.errors import UsageError

        limits = info.get("limits", {})
        try:
            return answered_count(limits if isinstance(limits, dict) else {"max_states": limits}, "max_states",
                                  f"{self.url}/stats") or None
        except BadAnswer as e:
            raise UsageError(f"{e}: is it an illm server? start one with `illm serve`") from None

    def _call(self, path: str, body: dict | None = None, timeout: float | None = None) -> dict:
        """The server's JSON object answer to GET (no body) or POST `path`. Redirects are not followed
        (an HTTPError: the token goes to the configured URL only); an answer that is not HTTP, not a
        JSON object (nested too deep to read included), or over `MAX_ANSWER_BYTES`, is a `BadAnswer`."""
        import json

        import http.client

        from illm_tools.annotate.wire import auth_headers

        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data=data, method="GET" if body is None else "POST",
                                         headers={"Content-Type": "application/json", **auth_headers(self._token)})
        try:
            with NO_REDIRECTS.open(request, timeout=timeout or self.timeout) as response:
                raw = response.read(MAX_ANSWER_BYTES + 1)
        except http.client.HTTPException as e:  # not HTTP (a status line of garbage): urllib lets it through
            if isinstance(e, ConnectionError):  # RemoteDisconnected: closed with no answer, a server going down
                raise
            raise BadAnswer(f"{self.url}{path} answered what is not HTTP ({type(e).__name__})") from None
        try:
            answer = json.loads(raw) if len(raw) <= MAX_ANSWER_BYTES else None
        except (ValueError, RecursionError):  # RecursionError: nested deeper than the decoder reads
            answer = None
        if not isinstance(answer, dict):
            raise BadAnswer(f"{self.url}{path} answered what is not a JSON object of at most {MAX_ANSWER_BYTES:,} bytes")
        return answer

    def server_stats(self, what: str = "") -> dict:
        """The server's GET /stats; at start (`what`), a server that does not answer, or refuses this
        run's token, is refused in one line."""
        import urllib.error

        from illm_tools.annotate.wire import TOKEN_ENV
        from illm_tools.errors import UsageError

        try:
            return self._call("/stats")
        except urllib.error.HTTPError as e:
            if e.code == 401:
                what = "refused this run's token" if self._token else "needs a token and this run has none"
                raise UsageError(f"the server at {self.url} {what}: pass the server's token with --annotator-token, or "
                                 f"set {TOKEN_ENV}") from None
            raise UsageError(f"the server at {self.url} answered {e.code} to GET /stats: is it an illm server? "
                             "start one with `illm serve`") from None
        except (urllib.error.URLError, OSError, ValueError) as e:
            raise UsageError(f"no illm server answers at {self.url} ({getattr(e, 'reason', e)}): start one with "
                             f"`illm serve --cache CACHE --model MODEL --port PORT`, or train without --annotator") from None

    def submit(self, missing: Sequence[StateRecord], visits: Sequence[int] | None = None) -> int:
        """Hand the first `budget` missed states (most visited first), with their visit counts, to the
        sender thread in place of a list it has not sent yet; returns at once with 0."""
        from illm_tools.annotate.wire import record_to_json

        limits = [n for n in (self.budget, self.max_states) if n is not None]
        limit = min(limits) if limits else None
        todo = list(missing[:limit])
        counts = list(visits[:limit]) if visits is not None else [1] * len(todo)
        states = [{**record_to_json(r), "visits": int(n)} for r, n in zip(todo, counts)]
        if self.waits:
            return self._send_now(states) if states else 0
        with self._lock:
            self._outbox = states
        self._wake.set()
        return 0

    def _send_now(self, states: list) -> int:
        """Sync: post `states` and wait for them to land (unless the server is in its back-off);
        returns the states of this run the server reports landed."""
        import time

        if time.monotonic() < self._not_before:
            return 0
        self._pace(self._send(states))
        return self.landed()

    def _pace(self, retry: float | None) -> None:
        """After a request: done (None) clears the back-off; otherwise the next is not sent before
        `retry` seconds (0: 1, 2, 4 ... `max_backoff` by the failures in a row)."""
        import time

        if retry is None:
            self._failures = 0
            return
        self._failures += 1
        self._not_before = time.monotonic() + (retry or min(self.max_backoff, 2.0 ** (self._failures - 1)))

    def _say(self, state: str, message: str, *args) -> None:
        """Log `message` when the server's state changes (once, not per rollout)."""
        if state != self._said:
            log.warning(message, *args)
        self._said = state

    def _sender(self) -> None:
        """The sender thread: the newest list to the server, backing off while it is down or busy."""
        import time

        while not self._closing.is_set():
            pause = self._not_before - time.monotonic()
            if pause > 0:  # backing off: a newer list waits too
                self._closing.wait(pause)
                continue
            self._wake.wait()
            self._wake.clear()
            with self._lock:
                states = self._outbox
            if states is None or self._closing.is_set():
                continue
            retry = self._send(states)
            self._pace(retry)
            if retry is None:  # done with this list (accepted, or refused for good)
                with self._lock:
                    if self._outbox is states:
                        self._outbox = None
            else:  # kept (unless a newer one replaces it) and tried again after the pause
                self._wake.set()

    def _send(self, states: list) -> float | None:
        """POST one list; None when done with it, else seconds to wait (0: back off by the failures)."""
        import json
        import urllib.error

        if self._said in ("down", "other"):  # a server answers again: is it still this run's model setup?
            changed = self._changed_server()
            if changed:
                self.counts["refused"] += 1
                self._say("other", "the annotation server at %s answers again but %s: this run's states are not sent "
                                   "to it; the run goes on with the targets the cache has", self.url, changed)
                return self.max_backoff
        self.counts["sent"] += 1
        try:
            wait = {"wait": self.wait} if self.waits else {}
            answer = self._call("/annotate", {**self.setup, "client": self.client, "session": self.session,
                                              "states": states, **wait}, timeout=self.timeout + self.wait)
            where = f"{self.url}/annotate"
            landed, queued, failed = (answered_count(answer, k, where) for k in ("landed", "queued", "failed"))
        except urllib.error.HTTPError as e:
            try:
                why = str(json.loads(e.read(MAX_ANSWER_BYTES)).get("error", ""))[:300]
            except (ValueError, AttributeError, OSError, RecursionError):
                why = ""
            if e.code in (429, 503):  # the server is full, or this run's client is over its share
                self.counts["busy"] += 1
                self._say("busy", "the annotation server at %s is full (%s); this run backs off and goes on training",
                          self.url, why)
                return retry_after(e.headers.get("Retry-After"))
            if e.code == 401:  # a restarted server with another token: it may get ours back
                self.counts["refused"] += 1
                self._say("refused", "the annotation server at %s refuses this run's token (%s); the run goes on "
                                     "with the targets the cache has", self.url, why)
                return self.max_backoff
            if e.code == 408:
                self.counts["unanswered"] += 1
                return 0.0
            if 300 <= e.code < 400:  # never followed: the token goes to the configured URL only
                self.counts["refused"] += 1
                self._say("refused", "the annotation server at %s answered a redirect (%s), which this run does not "
                                     "follow; the run goes on with the targets the cache has", self.url, e.code)
                return self.max_backoff
            self.counts["refused"] += 1  # 400, 409, 413: this list can never be accepted
            self._say("refused", "the annotation server refused this run's request (%s: %s); the run goes on with "
                                 "the targets the cache has", e.code, why[:300])
            return None
        except BadAnswer as e:
            self.counts["refused"] += 1
            self._say("malformed", "%s: not an illm server's answer; the run goes on with the targets the cache has",
                      e)
            return self.max_backoff
        except (urllib.error.URLError, OSError, ValueError) as e:
            self.counts["unanswered"] += 1
            self._say("down", "the annotation server at %s does not answer (%s); the run goes on with the targets the "
                              "cache has and sends its states again when it answers", self.url,
                      getattr(e, "reason", e))
            return 0.0
        self.counts["accepted"] += 1
        self._say("up", "the annotation server at %s answers again; this run's states are sent to it", self.url)
        if failed:  # states the server's engine could not annotate: said once per run
            self.counts["failed"] = self.counts.get("failed", 0) + failed
            if self.counts["failed"] == failed:
                log.warning("the annotation server could not annotate %s of this run's states (%s); the run goes on "
                            "without their targets", failed, str(answer.get("failure", ""))[:300])
        with self._lock:
            self._landed += landed
            self._queue = queued
        return None

    def _changed_server(self) -> str | None:
        """What differs in a server that answers again after being down (another protocol or model
        setup: a restart with other options), or None when it is the same or cannot tell yet."""
        try:
            info = self._call("/stats")
        except Exception:  # noqa: BLE001 - not answering yet: the request that follows says so
            return None
        from illm_tools.annotate.wire import PROTOCOL

        if info.get("protocol") != PROTOCOL:
            return f"speaks protocol {info.get('protocol')!r}, not this run's {PROTOCOL}"
        if info.get("model_fingerprint") != self.setup["model_fingerprint"]:
            return f"annotates with {info.get('model_options') or info.get('model')}, another model setup than this run's"
        return None

    @property
    def idle(self) -> bool:
        """Whether every list handed over has been sent (accepted, or refused for good)."""
        with self._lock:
            return self._outbox is None

    def landed(self) -> int:
        """States of this run the server put in the cache since the last call (reported with each request)."""
        with self._lock:
            landed, self._landed = self._landed, 0
        return landed

    def stats(self) -> dict[str, float]:
        return {"live_queue": float(self._queue)}

    def close(self, timeout: float = 2.0) -> None:
        """Stop the sender thread and withdraw this run's pending states from the server (best
        effort, at most `timeout` seconds: an absent server has nothing to withdraw)."""
        self._closing.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)  # a daemon: one stuck on a stalled server ends with the process
        try:
            self._call("/annotate", {**self.setup, "client": self.client, "session": self.session, "states": []},
                       timeout=timeout)
        except Exception:  # noqa: BLE001 - the run is over; an absent server has nothing to withdraw
            pass
