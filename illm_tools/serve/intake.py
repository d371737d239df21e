"""A request's way into `illm serve`'s queue (`Intake`): one sequence of checks, cheapest first,
whichever way the request comes:

1. `admit`: its fields, its model and setup, its wait, its number of states, and the quotas of
   trainers (`quotas.check_trainer`), before any state is read;
2. `parse_states`: each state checked against the server's setup (`ServerTerms.parse_state`), the
   request's own list of them dropped;
3. `quotas.check_queue`: the queue's quotas, before any state is measured;
4. `measure`: each state measured in tokens against the model's context (413);
5. `commit`: the quotas again (others may have been queued meanwhile), then the list queued
   (`AnnotationServer.enqueue`).

`take` runs it for a body as received over HTTP, the JSON and the costly steps in one checking
thread off the event loop (so `/stats` is answered meanwhile), one request's parsed form alive at a
time, its bytes dropped once parsed; `submit` runs the same steps for a parsed body in the caller's
thread (tests, in-process callers). `Pending` is a queued state, as the intake makes it.

The server is read through its own methods and attributes (`AnnotationServer`, named in the
annotations as text: it imports this module, so this one never imports it)."""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from illm_tools.annotate.wire import PROTOCOL
from illm_tools.serve.memory import release_free_memory
from illm_tools.serve.protocol import (MAX_ID_CHARS, REQUEST_FIELDS, RequestError, read_json, requested_wait, text,
                                       trainer_of, unknown_fields)
from illm_tools.serve.quotas import LOOPBACK, Asked, check_queue, check_trainer
from illm_tools.tasks.annotation_setup import AnnotationSetup
from illm_tools.tasks.state import StateRecord

LARGE = 2**20
"""A body of more bytes has what its parsing freed handed back to the system (as after a batch)."""


@dataclass
class Pending:
    """One state waiting, with the trainers that asked for it and their summed visits."""

    setup: AnnotationSetup
    record: StateRecord
    visits: int
    clients: set[tuple[str, str]] = field(default_factory=set)


async def _inline(work, *args):
    return work(*args)


class Intake:
    """The checks of a request and its queueing, in one sequence (module docstring)."""

    def __init__(self, server: AnnotationServer):
        self.server = server
        self._checker: ThreadPoolExecutor | None = None  # the one thread that parses and measures requests
        self._checking = asyncio.Lock()

    def submit(self, body, peer: str = LOOPBACK) -> dict:
        """Queue a parsed request body for its trainer (its list replaced) and answer: the steps of
        `take`, each in this thread; `peer`: the group of the address it came from (`config.peer_group`)."""
        steps = self._intake(body, peer, _inline)
        try:
            steps.send(None)  # nothing in it waits when every step runs inline
        except StopIteration as done:
            return done.value[0]
        steps.close()
        raise RuntimeError("an in-process request waited for another being checked: a running server takes "
                           "requests through `take`")

    async def take(self, raw: bytes | bytearray, peer: str) -> tuple[dict, tuple[str, str], float]:
        """A body as received, checked and queued without holding up the event loop (module
        docstring). Returns (answer, trainer, wait): all a wait needs; the caller passes `raw`
        without keeping it, and it is dropped once its states are parsed."""
        loop = asyncio.get_running_loop()
        if self._checker is None:
            self._checker = ThreadPoolExecutor(1, thread_name_prefix="illm-serve-check")

        def off(work, *args):
            return loop.run_in_executor(self._checker, work, *args)

        steps = self._intake(raw, peer, off)
        del raw  # the steps hold the body, and drop it once parsed
        answer, ask = await steps
        return answer, ask.trainer, ask.wait

    async def _intake(self, body, peer: str, off) -> tuple[dict, Asked]:
        """The one sequence (module docstring) for `body`, raw bytes or parsed; `off(work, *args)`
        awaits `work(*args)`, in the checking thread or inline."""
        async with self._checking:  # one body's parsed form alive at a time, whatever its size
            large = isinstance(body, (bytes, bytearray)) and len(body) > LARGE
            if isinstance(body, (bytes, bytearray)):
                body = await off(read_json, body)
            ask = self.admit(body, peer)
            del body  # `ask.states` is all that is left of it, and `parse_states` drops it
            entries = await off(self.parse_states, ask)
            if large:
                await off(release_free_memory)
        check_queue(self.server, ask, entries)
        await off(self.measure, ask, entries)
        return self.commit(ask, entries), ask

    def admit(self, body, peer: str = LOOPBACK) -> Asked:
        """The checks of a request that read no state: its fields, its model and setup, its wait, its
        number of states, and the quotas of trainers (`quotas.check_trainer`); RequestError otherwise."""
        server = self.server
        if not isinstance(body, dict):
            raise RequestError(400, "the request body must be a JSON object")
        missing = [k for k in ("client", "session", "model_fingerprint", "states") if k not in body]
        if missing:
            raise RequestError(400, f"the request lacks {', '.join(missing)} (a trainer of protocol {PROTOCOL} "
                                    "sends them: use the server's illm version)")
        unknown_fields(body, REQUEST_FIELDS, "the request")
        trainer = trainer_of(body)
        wait = requested_wait(body)
        text(body["model_fingerprint"], "model_fingerprint", MAX_ID_CHARS, 400)  # its type before anything reads it
        if body["model_fingerprint"] != server.fingerprint:
            raise RequestError(409, f"this server annotates with {server.llm.options()} (fingerprint "
                                    f"{server.fingerprint}); the request's fingerprint "
                                    f"{str(body['model_fingerprint'])[:80]!r} is another model setup: train with the "
                                    "server's --model, --dtype and --quant, or start a server for yours")
        setup = server.setup.of_request(body)
        states = body["states"]
        if not isinstance(states, list):
            raise RequestError(400, f"states must be a list, got {type(states).__name__}")
        if len(states) > server.limits.max_states:
            raise RequestError(413, f"a request carries at most {server.limits.max_states:,} states (the server's "
                                    f"--max-states), this one {len(states):,}: send the most visited first")
        ask = Asked(trainer, peer, setup, states, wait)
        check_trainer(server, ask)
        return ask

    def parse_states(self, ask: Asked) -> dict[tuple, Pending]:
        """The request's states, each checked (`ServerTerms.parse_state`), one entry per distinct state;
        the request's own list of them dropped (blocking: the checking thread runs it)."""
        states, ask.states = ask.states, None
        entries: dict[tuple, Pending] = {}
        for item in states:
            record, visits = self.server.setup.parse_state(item, ask.setup)
            entry = entries.setdefault((ask.setup, record), Pending(ask.setup, record, 0, {ask.trainer}))
            entry.visits += visits
        return entries

    def measure(self, ask: Asked, entries: dict[tuple, Pending]) -> None:
        """RequestError(413) when a state needs more tokens than the model's context (blocking: the
        checking thread runs it; the tokenizer's calls are the engine's, stateless)."""
        annotator = self.server.annotator
        for entry in entries.values():
            needed = annotator.state_too_long(entry.record, ask.setup.env_id, ask.setup.renderer)
            if needed is not None:
                raise RequestError(413, f"a state needs {needed:,} tokens, more than the context of the server's model "
                                        f"({annotator.context_length:,}): send shorter states (a shorter "
                                        "--history, shorter texts)")

    def commit(self, ask: Asked, entries: dict[tuple, Pending]) -> dict:
        """Queue `entries` as the trainer's list (none: withdraw it), every quota checked again (others
        may have been queued while its states were measured), and answer."""
        check_trainer(self.server, ask)
        if entries:
            check_queue(self.server, ask, entries)
        return self.server.enqueue(ask.trainer, ask.peer, entries)

    def close(self) -> None:
        """Drop a request being checked (the server stops)."""
        if self._checker is not None:
            self._checker.shutdown(wait=False, cancel_futures=True)
            self._checker = None
