"""Live annotation of the states a training run misses: in the trainer's process between rollouts
(`sync`), in a worker process beside the rollouts (`async`), or by an `illm serve` server shared
with other runs (`RemoteLive`, `--annotator URL`).

Both take, after each rollout, the run's missed states ordered most visited first (visits
counted over the run so far, `illm_tools.rl.targets`) and write their answers through the same
`Annotator` and cache API as `illm annotate`, so other runs sharing the cache benefit too.

- `SyncLive` annotates the first `budget` of them at once (None: all, `--live-budget all`); the
  trainer waits (about 1 s a state for SmolLM2 on 2 CPU cores, under a millisecond for the oracle)
  and uses them in this rollout.
- `AsyncLive` hands them to a worker process and returns at once. The worker keeps only the
  newest list (the trainer's priorities move as the run goes on), annotates it a few states per
  shard, most visited first, and the trainer uses whatever has landed in the cache by the next
  rollout. A worker that dies is restarted (at most `max_restarts` times, each logged as one
  line); after that the run goes on with the targets the cache has. The worker is a spawned
  process (not forked: a forked torch with live OpenMP threads can hang) with its own torch
  thread count, one core of a 2-core machine by default.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue
from collections.abc import Sequence
from dataclasses import dataclass

from illm_tools.llm.spec import LLMSpec
from illm_tools.tasks.setup import AnnotationSetup
from illm_tools.tasks.state import StateRecord

log = logging.getLogger(__name__)


class SyncLive:
    """Annotates the first `budget` missed states in the trainer's process (None: all of them)."""

    waits = True
    """The answers are in the cache when `submit` returns."""

    def __init__(self, annotator, setup: AnnotationSetup, budget: int | None, threads: int | None = None):
        self.annotator, self.setup, self.budget = annotator, setup, budget
        self.threads = threads
        """Torch threads of the LLM calls (the policy runs on fewer); None keeps the current count."""

    def submit(self, missing: Sequence[StateRecord], visits: Sequence[int] | None = None) -> int:
        """Annotate the first `budget` of `missing` (most visited first); returns how many."""
        from contextlib import nullcontext

        from illm_tools.rl.threads import torch_threads

        todo = list(missing[: self.budget])
        if not todo:
            return 0
        with torch_threads(self.threads) if self.threads else nullcontext():
            return self.annotator.annotate_states(todo, self.setup.env_id, self.setup.renderer).annotated_states

    def landed(self) -> int:
        """States annotated since the last call that `submit` did not count (none: it waits)."""
        return 0

    def stats(self) -> dict[str, float]:
        return {"live_queue": 0.0}

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class WorkerSpec:
    """Everything the worker process needs to rebuild the annotator (picklable, plain values)."""

    cache: str
    llm: LLMSpec
    """The run's LLM, placed (its device and dtype resolved)."""
    setup: AnnotationSetup
    """The run's key inputs besides the state (env, renderer, tasks, history, layout)."""
    threads: int
    batch_size: int = 8
    chunk: int = 8
    """States per written shard: small, so answers reach the trainer soon after they exist."""
    model_cache_dir: str | None = None


def _worker_main(spec: WorkerSpec, inbox, stop, queued, done, errors) -> None:  # pragma: no cover - child
    """The worker process. Ctrl-C reaches the whole process group: the worker ignores it and
    stops when the trainer sets `stop`. An error goes back to the trainer as one line."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        _work(spec, inbox, stop, queued, done)
    except Exception as e:  # noqa: BLE001 - reported to the trainer, which logs it as one line
        errors.put(f"{type(e).__name__}: {e}")
        raise SystemExit(1) from None


def _work(spec: WorkerSpec, inbox, stop, queued, done) -> None:  # pragma: no cover - runs in the child
    """Newest priority list in, shards out, until `stop` is set."""
    import torch

    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache

    torch.set_num_threads(spec.threads)
    lm = spec.llm.load(cache_dir=spec.model_cache_dir)
    annotator = Annotator.of_setup(lm, AnnotationCache(spec.cache), spec.llm, spec.setup, batch_size=spec.batch_size,
                                   chunk=spec.chunk)
    pending: list[StateRecord] = []
    while not stop.is_set():
        try:  # the newest list replaces the old one; wait for one when idle
            message = inbox.get(timeout=0.5) if not pending else inbox.get_nowait()
            while True:
                pending = list(message)
                message = inbox.get_nowait()
        except queue.Empty:
            pass
        queued.value = len(pending)
        if not pending:
            continue
        head, pending = pending[: spec.chunk], pending[spec.chunk:]
        annotator.cache.refresh()
        stats = annotator.annotate_states(head, spec.setup.env_id, spec.setup.renderer, should_stop=stop.is_set)
        with done.get_lock():
            done.value += stats.annotated_states
        queued.value = len(pending)


class AsyncLive:
    """A worker process that annotates the trainer's missed states while the rollouts go on."""

    waits = False

    def __init__(self, spec: WorkerSpec, *, budget: int | None, max_restarts: int = 3):
        self.spec, self.budget, self.max_restarts = spec, budget, max_restarts
        self._ctx = mp.get_context("spawn")
        self._queued = self._ctx.Value("l", 0)
        self._done = self._ctx.Value("l", 0)
        self._reported = 0
        self.restarts = 0
        self.failed = False
        self._start()

    def _start(self) -> None:
        self._inbox = self._ctx.Queue()
        self._errors = self._ctx.Queue()
        self._stop = self._ctx.Event()
        self.process = self._ctx.Process(target=_worker_main, name="illm-live-annotation", daemon=True,
                                         args=(self.spec, self._inbox, self._stop, self._queued, self._done,
                                               self._errors))
        self.process.start()

    def _check(self) -> bool:
        """True while a worker runs; restarts a dead one while restarts remain."""
        if self.failed:
            return False
        if self.process.is_alive():
            return True
        try:
            why = self._errors.get(timeout=0.1)
        except queue.Empty:
            why = f"exit code {self.process.exitcode}"
        if self.restarts >= self.max_restarts:
            self.failed = True
            log.warning("live annotation worker stopped (%s) %d times; the run goes on with the targets "
                        "the cache has", why, self.restarts + 1)
            return False
        self.restarts += 1
        log.warning("live annotation worker stopped (%s); restarting it (%d of %d)", why, self.restarts,
                    self.max_restarts)
        self._start()
        return True

    def submit(self, missing: Sequence[StateRecord], visits: Sequence[int] | None = None) -> int:
        """Hand the worker the first `budget` missed states (most visited first) in place of what
        it still had queued; returns at once (0: nothing is annotated before it returns)."""
        if self._check():
            self._inbox.put(list(missing[: self.budget]))
        return 0

    def landed(self) -> int:
        """States the worker annotated since the last call."""
        if not hasattr(self, "_done"):  # closed
            return 0
        done = self._done.value
        landed, self._reported = done - self._reported, done
        return landed

    def stats(self) -> dict[str, float]:
        if not hasattr(self, "_queued"):  # closed
            return self._last_stats
        return {"live_queue": float(self._queued.value), "live_worker_restarts": float(self.restarts)}

    def close(self, timeout: float = 30.0) -> None:
        """Ask the worker to stop after its current chunk (written whole or not at all); end it
        if it does not within `timeout` seconds. Every shard it wrote stays valid."""
        self._stop.set()
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(5.0)
        for q in (self._inbox, self._errors):
            q.close()
            q.cancel_join_thread()  # a worker gone without reading leaves data in the pipe: do not wait for it
        self.exitcode = self.process.exitcode  # the process object is closed below: what it ended with stays
        self.process.close()
        # Release the shared objects' semaphores now: left to interpreter shutdown, their finalizers may
        # run after the resource tracker's check, which then warns about "leaked semaphore objects".
        self._last_stats = self.stats()
        for name in ("_inbox", "_errors", "_stop", "_queued", "_done"):
            delattr(self, name)
        import gc

        gc.collect()


class RemoteLive:
    """Live annotation by an `illm serve` server (`illm train --annotator URL`): after each rollout
    the first `budget` missed states, with their visit counts, go to the server, which annotates
    them for every trainer it serves into the shared cache; a later rollout finds the answers there.

    The client is the standard library's `urllib` (one short JSON POST per rollout, no connection
    kept: no reason for another dependency on the trainer's side). A server that cannot be reached
    when the run starts is refused in one line; one that stops answering later is logged once,
    and the run goes on with the targets the cache has (retrying each rollout)."""

    waits = False

    def __init__(self, url: str, *, client: str, llm: LLMSpec, setup: AnnotationSetup, budget: int | None,
                 timeout: float = 10.0):
        self.url = url.rstrip("/")
        self.client, self.budget, self.timeout = client, budget, timeout
        self.setup = {**setup.wire(), "model_fingerprint": llm.fingerprint()}
        """The request's fields besides the client and the states (`AnnotationSetup.wire`)."""
        self._landed = 0
        self._queue = 0
        self._down = False
        info = self.server_stats(what="start")
        if info.get("model_fingerprint") != self.setup["model_fingerprint"]:
            from illm_tools.errors import UsageError

            raise UsageError(f"the server at {self.url} annotates with {info.get('model_options') or info.get('model')}, "
                             f"another model setup than this run's {llm.options()}: its answers would never be this run's "
                             "targets; train with the server's options or start a server for this model")

    def _call(self, path: str, body: dict | None = None) -> dict:
        import json
        import urllib.request

        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data=data, method="GET" if body is None else "POST",
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=self.timeout) as response:
            return json.loads(response.read())

    def server_stats(self, what: str = "") -> dict:
        """The server's GET /stats; at start (`what`), a server that does not answer is refused in one line."""
        import urllib.error

        try:
            return self._call("/stats")
        except (urllib.error.URLError, OSError, ValueError) as e:
            from illm_tools.errors import UsageError

            raise UsageError(f"no illm server answers at {self.url} ({getattr(e, 'reason', e)}): start one with "
                             f"`illm serve --cache CACHE --model MODEL --port PORT`, or train without --annotator") from None

    def submit(self, missing: Sequence[StateRecord], visits: Sequence[int] | None = None) -> int:
        """Send the first `budget` missed states (most visited first) with their visit counts in
        place of what this run still had queued there; returns at once with 0."""
        import urllib.error

        from illm_tools.annotate.wire import record_to_json

        todo = list(missing[: self.budget])
        counts = list(visits[: self.budget]) if visits is not None else [1] * len(todo)
        states = [{**record_to_json(r), "visits": int(n)} for r, n in zip(todo, counts)]
        try:
            answer = self._call("/annotate", {**self.setup, "client": self.client, "states": states})
        except urllib.error.HTTPError as e:  # the server refused the request: a bug on this side, said once
            if not self._down:
                log.warning("the annotation server refused this run's request (%s: %s); the run goes on with the "
                            "targets the cache has", e.code, e.read().decode(errors="replace")[:300])
            self._down = True
            return 0
        except (urllib.error.URLError, OSError, ValueError) as e:
            if not self._down:
                log.warning("the annotation server at %s does not answer (%s); the run goes on with the targets the "
                            "cache has and tries again each rollout", self.url, getattr(e, "reason", e))
            self._down = True
            return 0
        if self._down:
            log.warning("the annotation server at %s answers again", self.url)
        self._down = False
        self._landed += int(answer.get("landed", 0))
        self._queue = int(answer.get("queued", 0))
        return 0

    def landed(self) -> int:
        """States of this run the server put in the cache since the last call (reported with each request)."""
        landed, self._landed = self._landed, 0
        return landed

    def stats(self) -> dict[str, float]:
        return {"live_queue": float(self._queue)}

    def close(self) -> None:
        """Withdraw this run's pending states from the server (best effort)."""
        try:
            self._call("/annotate", {**self.setup, "client": self.client, "states": []})
        except Exception:  # noqa: BLE001 - the run is over; an absent server has nothing to withdraw
            pass
