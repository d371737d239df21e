"""`AnnotationServer`: the queue, the fair scheduler and the model behind `illm serve` (the HTTP side
is `illm_tools.serve.http`).

Queue. Each trainer, named by `client` (its run) and `session` (a random id it makes), has one
pending list, replaced by its newest request, checked whole before anything is queued (`intake`:
the request's fields and the trainer quotas, its states parsed, the queue quotas, its states
measured in tokens, in that order, off the event loop) and within the quotas (`quotas`, which read
the queue through `queued`, `peer_of`, `is_waiting` and `waiting_from` only).

Scheduling. Round-robin across peers (`config.peer_group`), then across a peer's client names,
least recently served first, one state per turn until the batch holds `chunk` (`batch.take_turns`);
the visits a client declares only order its own states, so no count buys a place before another
client's, and no invented name a turn before another peer's. A state two trainers both asked for is annotated once.

Faults. A batch runs in a daemon thread with a deadline (`batch_deadline`): past it, its states are
answered as failed and no batch starts until the engine returns (requests are still answered); a
stop waits for the batch in progress at most until its deadline. A batch that raises is retried
state by state: a state failing in the engine is answered to its trainers (`failed`, `failure` in
their next answer) and counted, and every other state lands.

Waiting. A request may ask to be answered once its states have landed (`"wait": seconds`, at most
`MAX_WAIT`): a trainer in `--live-mode sync` uses the answers in the rollout that asked for them, as
with an annotator of its own, whatever the machine's speed (`settled`). A waiting request holds its
trainer's name, nothing of its body; one waits per trainer (a newer one answers the older at once),
and a client gone cancels its wait (the HTTP side's handler cancellation).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Mapping, Sequence, Set
from dataclasses import asdict
from types import MappingProxyType

from illm_tools.annotate.wire import PROTOCOL
from illm_tools.llm.spec import LLMSpec
from illm_tools.serve.config import ServeConfig, ServeLimits
from illm_tools.serve.batch import annotate_batch, in_thread, one_line, take_turns
from illm_tools.serve.intake import Intake, Pending
from illm_tools.serve.memory import resident_mb
from illm_tools.serve.protocol import ServerTerms
from illm_tools.serve.quotas import LOOPBACK
from illm_tools.tasks.prompt_config import PromptConfig

log = logging.getLogger(__name__)

MAX_RETRY_AFTER = 60
"""Longest Retry-After a busy server answers (seconds)."""


class AnnotationServer:
    """The queue, the scheduler and the model behind `illm serve` (module docstring)."""

    def __init__(self, lm, cache, *, llm: LLMSpec, prompt: PromptConfig | None = None,
                 tasks: Sequence[str] = ("action", "summary"), batch_size: int = ServeConfig.batch_size, chunk: int = ServeConfig.chunk,
                 limits: ServeLimits | None = None):
        from illm_tools.annotate.engine import Annotator
        from illm_tools.llm.backend import as_backend

        self.lm = as_backend(lm)
        self.cache = cache
        self.llm = llm  # the model as it was loaded (placed: its device and dtype resolved)
        self.model = llm.model
        self.limits = limits or ServeLimits()
        self.setup = ServerTerms(llm, prompt=prompt or PromptConfig(), tasks=tuple(tasks), limits=self.limits)
        """The setup every row this server writes carries, and the request checks."""
        self.batch_size, self.chunk = batch_size, chunk
        # one annotator: the server's tasks, history and layout (the backend's ranking check runs here, at start)
        self.annotator = Annotator.of_setup(self.lm, cache, llm, self.setup.prompt, tasks=self.setup.tasks,
                                            batch_size=batch_size, chunk=chunk)
        self.annotating = 0
        """States in the batch being annotated now (0: idle)."""
        self.connections = 0  # open now (kept by the HTTP side's gate)
        self.fingerprint = self.annotator.model_fingerprint  # what the rows it writes carry
        self._clients: dict[tuple[str, str], dict[tuple, Pending]] = {}  # trainer -> its own pending list
        self._landed: dict[tuple[str, str], int] = {}
        self._failed: dict[tuple[str, str], tuple[int, str]] = {}  # trainer -> (states failed, last reason)
        self._seen: dict[tuple[str, str], float] = {}  # when each trainer last sent (to forget the gone)
        self._served: dict[tuple[str, str], int] = {}  # (peer, client name) -> the round it last got a state
        self._served_peer: dict[str, int] = {}  # peer -> the round it last got a state (round-robin)
        self._peer: dict[tuple[str, str], str] = {}  # trainer -> the peer its requests come from
        self._round = 0
        self._in_engine: set[tuple[str, str]] = set()  # trainers with states in the batch in progress
        self._waiters: dict[tuple[str, str], tuple[asyncio.Event, str]] = {}  # trainer -> (its waiter, its peer)
        self.intake = Intake(self)
        """A request's way into the queue (`Intake.take` for those over HTTP)."""
        self._stuck: asyncio.Future | None = None  # a batch past its deadline, still in the engine
        self._wake = asyncio.Event()
        self._stop: asyncio.Event | None = None
        self.started = time.time()
        self.totals = {"states": 0, "rows": 0, "batches": 0, "requests": 0, "refused": 0, "busy": 0,
                       "throttled": 0, "unauthorized": 0, "forbidden": 0, "timeouts": 0, "connections_refused": 0,
                       "connections_evicted": 0, "seconds": 0.0, "errors": 0, "failed_states": 0, "late_batches": 0}
        self.last_error: str | None = None

    @classmethod
    def of_config(cls, lm, cache, llm: LLMSpec, config: ServeConfig) -> AnnotationServer:
        """The server of a `ServeConfig` (its setup, batching and limits) with a loaded model."""
        return cls(lm, cache, llm=llm, prompt=config.setup, tasks=config.tasks, batch_size=config.batch_size,
                   chunk=config.chunk, limits=config.limits)

    @property
    def stopping(self) -> bool:
        """Whether a stop was asked: the batch in progress is finished, nothing more is queued."""
        return self._stop is not None and self._stop.is_set()

    def retry_after(self) -> int:
        """Seconds a refused trainer should wait: about one batch's time at the throughput so far."""
        rate = self.totals["states"] / self.totals["seconds"] if self.totals["seconds"] else 0.0
        return min(MAX_RETRY_AFTER, max(1, math.ceil(self.chunk / rate))) if rate else 5

    # --- requests ------------------------------------------------------------------------------
    def submit(self, body, peer: str = LOOPBACK) -> dict:
        """Queue a parsed request body for its trainer, in this thread (tests, in-process callers): the
        steps a request over HTTP takes (`Intake`); `peer`: the group of the address it came from."""
        return self.intake.submit(body, peer)

    def enqueue(self, trainer: tuple[str, str], peer: str, entries: dict[tuple, Pending]) -> dict:
        """Queue `entries` as `trainer`'s list (none: withdraw it) and answer its request: the intake's
        last step, once every check has passed (`Intake.commit`)."""
        self.totals["requests"] += 1
        self._seen[trainer] = time.monotonic()
        if entries:
            self._clients[trainer] = entries
            self._peer[trainer] = peer
            self._wake.set()
        else:  # withdrawn: the trainer is done
            self._clients.pop(trainer, None)
            self._seen.pop(trainer, None)
            self._peer.pop(trainer, None)
            self._wake_waiters()
        self._forget_gone()
        answer = {"queued": len(entries), "queue": self.queue_size(), "landed": self._landed.pop(trainer, 0)}
        failed = self._failed.pop(trainer, None)
        if failed:
            answer.update(failed=failed[0], failure=failed[1])
        return answer

    def pending_for(self, trainer: tuple[str, str]) -> bool:
        """Whether some state of `trainer`'s is queued or in the engine now."""
        return trainer in self._clients or trainer in self._in_engine

    @property
    def waiting(self) -> int:
        """Requests held now until their states land (`settled`)."""
        return len(self._waiters)

    async def settled(self, trainer: tuple[str, str], timeout: float, peer: str = LOOPBACK) -> dict:
        """Wait (at most `timeout` seconds) until none of `trainer`'s states is queued or in the engine,
        then take what became of them since its answer: {"landed"[, "failed", "failure"], "queue"}.
        One waiter per trainer: a newer one answers the older at once (`pending`, nothing taken); a
        waiter cancelled (its client gone) leaves nothing behind."""
        if timeout > 0 and self.pending_for(trainer):
            older = self._waiters.get(trainer)
            if older is not None:
                older[0].set()
            event = asyncio.Event()
            self._waiters[trainer] = (event, peer)
            try:
                await asyncio.wait_for(event.wait(), timeout)
            except asyncio.TimeoutError:
                pass
            finally:
                if self._waiters.get(trainer, (None,))[0] is event:
                    del self._waiters[trainer]
            if trainer in self._waiters:  # a newer request of this trainer waits: it takes the answers
                return {"landed": 0, "queue": self.queue_size(), "pending": True}
        answer = {"landed": self._landed.pop(trainer, 0), "queue": self.queue_size(),
                  "pending": self.pending_for(trainer)}
        failed = self._failed.pop(trainer, None)
        if failed:
            answer.update(failed=failed[0], failure=failed[1])
        return answer

    def _wake_waiters(self) -> None:
        for trainer, (event, _) in self._waiters.items():
            if not self.pending_for(trainer):
                event.set()

    def _forget_gone(self) -> None:
        """Drop what is kept of trainers that went away without withdrawing (their landed and failed
        counts, their clients' turns) once there are many: those with no pending list, longest unseen first."""
        keep = 2 * self.limits.max_clients
        if len(self._seen) > 2 * keep:
            idle = sorted((t, who) for who, t in self._seen.items() if who not in self._clients)
            for _, who in idle[: len(self._seen) - keep]:
                self._seen.pop(who, None)
                self._landed.pop(who, None)
                self._failed.pop(who, None)
                self._peer.pop(who, None)
        for served, queued in ((self._served, {(self._peer.get(w, LOOPBACK), w[0]) for w in self._clients}),
                               (self._served_peer, {self._peer.get(w, LOOPBACK) for w in self._clients})):
            if len(served) > 2 * keep:
                for lane in sorted(served, key=served.get)[: len(served) - keep]:
                    if lane not in queued:
                        del served[lane]

    def queue_size(self) -> int:
        return len({k for entries in self._clients.values() for k in entries})

    # --- what the quotas read (`quotas`) -----------------------------------------------------------
    def queued(self) -> Mapping[tuple[str, str], Set[tuple]]:
        """Each trainer with a list queued -> the keys of its states (read-only)."""
        return MappingProxyType({trainer: entries.keys() for trainer, entries in self._clients.items()})

    def peer_of(self, trainer: tuple[str, str]) -> str | None:
        """The peer `trainer`'s session is tied to: the one its queued list or its waiting request came
        from; None with neither (its next request's peer takes it)."""
        if trainer in self._clients:
            return self._peer.get(trainer, LOOPBACK)
        waiter = self._waiters.get(trainer)
        return waiter[1] if waiter is not None else None

    def is_waiting(self, trainer: tuple[str, str]) -> bool:
        """Whether a request of `trainer`'s waits for its states now (`settled`)."""
        return trainer in self._waiters

    def waiting_from(self, peer: str) -> int:
        """Requests from `peer` waiting for their states now."""
        return sum(1 for _, at in self._waiters.values() if at == peer)

    def stats(self) -> dict:
        """The queue, totals, throughput, setup and limits (GET /stats)."""
        t, busy, up = self.totals, self.totals["seconds"], time.time() - self.started
        return {"protocol": PROTOCOL, "model": self.model, "model_options": self.llm.options(),
                "model_fingerprint": self.fingerprint, "setup": self.setup.describe(), "cache": str(self.cache.root),
                "queue": self.queue_size(), "annotating": self.annotating, "clients": len(self._clients),
                "connections": self.connections, "waiting": self.waiting,
                "annotated_states": t["states"], "rows": t["rows"], "batches": t["batches"], "requests": t["requests"],
                **{k: t[k] for k in ("refused", "busy", "throttled", "unauthorized", "forbidden", "timeouts",
                                     "connections_refused", "connections_evicted", "errors", "failed_states", "late_batches")},
                "last_error": self.last_error, "stopping": self.stopping, "limits": asdict(self.limits),
                "states_per_s": t["states"] / busy if busy else 0.0,
                "states_per_s_since_start": t["states"] / up if up else 0.0, "uptime_s": up,
                "resident_mb": resident_mb()}

    # --- the scheduler ---------------------------------------------------------------------------
    def next_batch(self) -> list[Pending]:
        """Take up to `chunk` pending states, round-robin across peers (`config.peer_group`), then
        across the client names of a peer, least recently served first, each client's own states
        most visited first; a state asked by several trainers is one entry with all of them. A peer
        gets one state a turn however many names it sends under."""
        lanes: dict[tuple[str, str], dict[tuple, Pending]] = {}  # (peer, client name) -> its states
        for trainer, entries in self._clients.items():
            mine = lanes.setdefault((self._peer.get(trainer, LOOPBACK), trainer[0]), {})
            for key, entry in entries.items():
                have = mine.get(key)
                if have is None:
                    mine[key] = Pending(entry.setup, entry.record, entry.visits, set())
                else:
                    have.visits += entry.visits
        self._round += 1
        batch = take_turns(lanes, self._served, self._served_peer, self._round, self.chunk)
        for trainer in list(self._clients):
            entries = self._clients[trainer]
            for key in batch.keys() & entries.keys():
                batch[key].clients.add(trainer)
                del entries[key]
            if not entries:
                del self._clients[trainer]
        return list(batch.values())

    def annotate(self, batch: Sequence[Pending]) -> tuple[int, int, list[tuple[Pending, str]]]:
        """Annotate a batch (blocking: `illm_tools.serve.batch.annotate_batch`)."""
        return annotate_batch(self.annotator, batch)

    def _answer(self, batch: Sequence[Pending], failed: Sequence[tuple[Pending, str]]) -> None:
        """Tell each trainer of the batch what became of its states: landed, or failed with the reason."""
        bad = {id(p) for p, _ in failed}
        for p, reason in failed:
            self.totals["failed_states"] += 1
            for trainer in p.clients:
                n, _ = self._failed.get(trainer, (0, ""))
                self._failed[trainer] = (n + 1, reason)
        for p in batch:  # in the cache now (annotated, or already there): landed for each asker still here
            if id(p) not in bad:
                for trainer in p.clients & self._seen.keys():
                    self._landed[trainer] = self._landed.get(trainer, 0) + 1

    async def _wait(self, aws) -> None:
        await asyncio.wait([asyncio.ensure_future(a) for a in aws], return_when=asyncio.FIRST_COMPLETED)

    async def run(self, stop: asyncio.Event) -> None:
        """Annotate batches until `stop` is set; the batch in progress is finished first, waiting at
        most until its deadline (requests meanwhile are refused with 503: `stopping`)."""
        self._stop = stop
        stopper = asyncio.ensure_future(stop.wait())
        try:
            while not stop.is_set():
                if self._stuck is not None:  # the engine still holds a late batch: no other may start
                    await self._wait([self._stuck, stopper])
                    if self._stuck.done():
                        self._stuck = None
                    continue
                batch = self.next_batch()
                if not batch:
                    self._wake.clear()
                    waiter = asyncio.ensure_future(self._wake.wait())
                    await self._wait([waiter, stopper])
                    waiter.cancel()
                    continue
                await self._run_batch(batch)
        finally:
            stopper.cancel()
            self.intake.close()  # a request being checked is dropped: the server stops

    async def _run_batch(self, batch: list[Pending]) -> None:
        self._in_engine = {trainer for p in batch for trainer in p.clients}
        try:
            await self._annotate_batch(batch)
        finally:
            self._in_engine = set()
            self._wake_waiters()

    async def _annotate_batch(self, batch: list[Pending]) -> None:
        start = time.perf_counter()
        self.annotating = len(batch)
        future = in_thread(lambda: self.annotate(batch), "illm-serve-batch")
        deadline = self.limits.batch_deadline
        try:
            await asyncio.wait([future], timeout=deadline)
        finally:
            self.annotating = 0
        if not future.done():
            self._stuck = future
            self.totals["late_batches"] += 1
            reason = f"the engine took longer than the server's --batch-deadline {deadline:g} s"
            self._answer([], [(p, reason) for p in batch])
            self.last_error = reason
            log.warning("a batch of %d states is past its deadline (%g s): its states are answered as failed",
                        len(batch), deadline)
            return
        try:
            done, rows, failed = future.result()
        except Exception as e:  # noqa: BLE001 - the batch thread's own fault: the server goes on
            self.totals["errors"] += 1
            self.last_error = one_line(e)
            log.warning("a batch of %d states failed (%s); the server goes on", len(batch), self.last_error)
            self._answer([], [(p, self.last_error) for p in batch])
            return
        self.totals["seconds"] += time.perf_counter() - start
        self.totals["states"] += done
        self.totals["rows"] += rows
        self.totals["batches"] += 1
        if failed:
            self.last_error = failed[-1][1]
            log.warning("%d of a batch's %d states failed in the engine (%s); the others landed", len(failed),
                        len(batch), self.last_error)
        self._answer(batch, failed)
