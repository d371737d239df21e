"""Live annotation of the states a training run misses: in the trainer's process between rollouts
(`sync`), in a worker process beside the rollouts (`async`), or by an `illm serve` server shared
with other runs (`RemoteLive`, `--annotator URL`: `illm_tools.rl.live_remote`).

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
  thread count, one core of a 2-core machine by default. `illm train` starts it first, from its
  options, before this process imports torch (`illm_tools.rl.run.early_live_of_settings`): it
  imports torch and transformers' loading code while the trainer builds its config, env pool and
  network, takes its spec once the run is configured, then loads the model from the de-quantised
  safetensors, memory-mapped; its start-up is logged as `live_worker_startup_s`. Its first shards
  are small (1 state, then 2, 4, ... up to `chunk`), so the first answer lands about one state's
  annotation after the model is loaded, logged as `live_first_answer_s` (from the worker's spawn,
  a third of a second into `illm train`). On a 2-core EPYC with SmolLM2 that is about 4.5 s (6.6-11 s
  on a 2-core Xeon at half its single-core rate, most of it importing transformers' Llama code): an
  8,192-frame run of the demo's level gets 1-2 states in its last rollouts on the EPYC, and on the
  Xeon none in 2 runs of 6 (docs/measured.md). No answer lands
  before the model is loaded, so a run of a few rollouts gets few live targets in this mode
  (`--live-budget all` promises every step only with sync; `illm train` says so before such a run
  starts).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue
from collections.abc import Sequence
from dataclasses import dataclass

from illm_tools.llm.spec import LLMSpec
from illm_tools.signals import ctrl_c_deferred
from illm_tools.tasks.annotation_setup import AnnotationSetup
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
        self.too_long = 0
        """Missed states refused for being longer than the model's context (the annotator logs the first)."""

    def submit(self, missing: Sequence[StateRecord], visits: Sequence[int] | None = None) -> int:
        """Annotate the first `budget` of `missing` (most visited first); returns how many."""
        from contextlib import nullcontext

        from illm_tools.rl.threads import torch_threads

        todo = list(missing[: self.budget])
        if not todo:
            return 0
        with torch_threads(self.threads) if self.threads else nullcontext():
            stats = self.annotator.annotate_states(todo, self.setup.env_id, self.setup.renderer)
        self.too_long += len(stats.too_long)  # logged once by the annotator
        return stats.annotated_states

    def landed(self) -> int:
        """States annotated since the last call that `submit` did not count (none: it waits)."""
        return 0

    def stats(self) -> dict[str, float]:
        return {"live_queue": 0.0, **({"live_too_long": float(self.too_long)} if self.too_long else {})}

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
    """States per written shard, at most: small, so answers reach the trainer soon after they exist
    (the first shards smaller still: 1 state, then 2, 4, ..., `first_chunks`)."""
    model_cache_dir: str | None = None


def first_chunks(chunk: int, written: int) -> int:
    """States in the worker's next shard after `written` shards: 1, 2, 4, ... up to `chunk`, so
    the first answer lands one state's annotation after the model is loaded, and the later shards
    are as few as `chunk` makes them."""
    return max(1, min(chunk, 1 << min(written, 30)))


def _worker_main(llm: LLMSpec, setup, inbox, stop, queued, done, errors, ready,
                 first) -> None:  # pragma: no cover - runs in the child
    """The worker process: what loading `llm` will import first (`LLMSpec.preload`), then its spec
    from `setup` (sent once the run is configured), then the work. Ctrl-C reaches the whole process
    group: the worker ignores it and stops when the trainer sets `stop`. An error goes back to the
    trainer as one line."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        llm.preload()
        spec = _configured(setup, stop)
        if spec is not None:
            _work(spec, inbox, stop, queued, done, ready, first)
    except Exception as e:  # noqa: BLE001 - reported to the trainer, which logs it as one line
        errors.put(f"{type(e).__name__}: {e}")
        raise SystemExit(1) from None


def _stopping(stop) -> bool:  # pragma: no cover - runs in the child
    """Whether the worker should stop: the trainer set `stop`, or the trainer is gone without
    setting it (killed: a worker left behind would hold its core and memory)."""
    parent = mp.parent_process()
    return stop.is_set() or (parent is not None and not parent.is_alive())


def _configured(setup, stop) -> WorkerSpec | None:  # pragma: no cover - runs in the child
    """The spec `AsyncLive.configure` sends, or None when the trainer stops the worker first."""
    while not _stopping(stop):
        try:
            return setup.get(timeout=0.2)
        except queue.Empty:
            continue
    return None


def _work(spec: WorkerSpec, inbox, stop, queued, done, ready, first) -> None:  # pragma: no cover - runs in the child
    """Newest priority list in, shards out, until `stop` is set (or the trainer is gone); `ready` gets the wall time at which
    the model is loaded and the worker takes its first list, `first` the time its first answer is
    in the cache (unless an earlier start of the worker set it)."""
    import time

    import torch

    from illm_tools.annotate.engine import Annotator
    from illm_tools.cache.store import AnnotationCache

    torch.set_num_threads(spec.threads)
    lm = spec.llm.load(cache_dir=spec.model_cache_dir)
    annotator = Annotator.of_setup(lm, AnnotationCache(spec.cache), spec.llm, spec.setup, batch_size=spec.batch_size,
                                   chunk=spec.chunk)
    ready.value = time.time()
    pending: list[StateRecord] = []
    written = 0
    while not _stopping(stop):
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
        size = first_chunks(spec.chunk, written)
        head, pending = pending[:size], pending[size:]
        annotator.cache.refresh()
        stats = annotator.annotate_states(head, spec.setup.env_id, spec.setup.renderer,
                                          should_stop=lambda: _stopping(stop))
        written += 1
        with done.get_lock():
            done.value += stats.annotated_states
        if stats.annotated_states and not first.value:
            first.value = time.time()
        queued.value = len(pending)


class AsyncLive:
    """A worker process that annotates the trainer's missed states while the rollouts go on.

    The worker first imports what loading the model will (`LLMSpec.preload`), then takes its spec.
    Made with its `spec`, it has it at once. Made with `early` (the run's LLM, not yet placed)
    instead, it starts before the run is configured and waits for `configure(spec)`
    (`illm_tools.rl.run.train` starts it before the trainer imports torch)."""

    waits = False

    def __init__(self, spec: WorkerSpec | None = None, *, budget: int | None, max_restarts: int = 3,
                 early: LLMSpec | None = None):
        if (spec is None) == (early is None):
            raise ValueError("AsyncLive takes its spec, or the LLM it preloads until `configure` sends the spec")
        self.spec, self.budget, self.max_restarts = None, budget, max_restarts
        self.llm = early if early is not None else spec.llm
        self._ctx = mp.get_context("spawn")
        self._queued = self._ctx.Value("l", 0)
        self._done = self._ctx.Value("l", 0)
        self._ready = self._ctx.Value("d", 0.0)
        self._first = self._ctx.Value("d", 0.0)
        self._reported = 0
        self.restarts = 0
        self.failed = False
        self._start()
        self.opened_at = self.started_at
        """When the first worker was spawned (the run's start: `train` starts it first)."""
        if spec is not None:
            self.configure(spec, budget=budget)

    def configure(self, spec: WorkerSpec, *, budget: int | None) -> None:
        """Send the worker its spec (it loads the model once its imports are done) and set the
        run's budget."""
        if self.spec is not None:
            raise ValueError("this live worker has its spec already")
        self.spec, self.budget = spec, budget
        self._setup.put(spec)

    def _start(self) -> None:
        """Spawn a worker: a restarted one gets the spec at once."""
        import time

        self.started_at = time.time()
        self._ready.value = 0.0
        self._setup = self._ctx.Queue()
        self._inbox = self._ctx.Queue()
        self._errors = self._ctx.Queue()
        self._stop = self._ctx.Event()
        self.process = self._ctx.Process(target=_worker_main, name="illm-live-annotation", daemon=True,
                                         args=(self.llm, self._setup, self._inbox, self._stop, self._queued,
                                               self._done, self._errors, self._ready, self._first))
        # a Ctrl-C reaches the whole process group: one landing while the worker's interpreter starts (before
        # `_worker_main` ignores it) would end in its traceback, and one raised here in the middle of the spawn
        # would leave the worker half started. Deferred: the worker inherits the block (the trainer stops it
        # itself, `stop`), and a Ctrl-C that came meanwhile reaches this process once the worker has started
        with ctrl_c_deferred():
            self.process.start()
        if self.spec is not None:
            self._setup.put(self.spec)

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
        """States the worker annotated since the last call (after `close`, those of its last chunk too)."""
        done = self._done.value if hasattr(self, "_done") else self._final_done
        landed, self._reported = done - self._reported, done
        return landed

    def stats(self) -> dict[str, float]:
        if not hasattr(self, "_queued"):  # closed
            return self._last_stats
        ready, first = self._ready.value, self._first.value
        return {"live_queue": float(self._queued.value), "live_worker_restarts": float(self.restarts),
                **({"live_worker_startup_s": ready - self.started_at} if ready else {}),
                **({"live_first_answer_s": first - self.opened_at} if first else {})}

    def close(self, timeout: float = 30.0) -> None:
        """Ask the worker to stop after its current chunk (written whole or not at all); end it
        if it does not within `timeout` seconds (at once if it never got its spec: it has written
        nothing). Every shard it wrote stays valid. Closing twice does nothing."""
        if not hasattr(self, "_stop"):
            return
        self._stop.set()
        self.process.join(timeout if self.spec is not None else 0.0)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(5.0)
        for q in (self._inbox, self._errors, self._setup):
            q.close()
            q.cancel_join_thread()  # a worker gone without reading leaves data in the pipe: do not wait for it
        self.exitcode = self.process.exitcode  # the process object is closed below: what it ended with stays
        self.process.close()
        # Release the shared objects' semaphores now: left to interpreter shutdown, their finalizers may
        # run after the resource tracker's check, which then warns about "leaked semaphore objects".
        self._last_stats = self.stats()
        self._final_done = self._done.value  # the worker's last chunk, written while it stopped, is counted
        for name in ("_inbox", "_errors", "_setup", "_stop", "_queued", "_done", "_ready", "_first"):
            delattr(self, name)
        import gc

        gc.collect()
