"""One batch of the server's pending states: which states it takes (`take_turns`), and their way
through the annotator, in a thread of its own.

`take_turns` is the fair order: round-robin across peers (a peer's client names share its turn),
then across a peer's client names, least recently served first, each name's states most visited
first, one state a turn until the batch is full; a state already taken is skipped.

`annotate_batch` writes what the cache lacks of the batch, one shard per setup; a batch that
raises is tried again state by state, so one state's fault costs the others nothing. `in_thread`
runs it as a daemon thread whose result the event loop awaits (a stop need not wait for it past
the batch's deadline: `illm_tools.serve.scheduler`).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Sequence

from illm_tools.serve.memory import release_free_memory

MAX_HOP_CONTEXTS = 4
"""Hop translations (projections) the annotator keeps between batches; beyond, they are rebuilt."""


def take_turns(lanes: dict, served: dict, served_peer: dict, round_: int, chunk: int) -> dict:
    """The batch {(setup, record): Pending} of at most `chunk` states from `lanes` ({(peer, client
    name): {key: Pending}}), in the fair order (module docstring); `served` (by lane) and
    `served_peer` (by peer) record `round_` for those served."""
    by_peer: dict[str, list] = {}
    for lane in sorted(lanes, key=lambda lane: served.get(lane, -1)):  # stable: ties in arrival order
        by_peer.setdefault(lane[0], []).append(lane)
    peers = sorted(by_peer, key=lambda peer: served_peer.get(peer, -1))
    lists = {lane: sorted(states.values(), key=lambda p: -p.visits) for lane, states in lanes.items()}
    at, turn = dict.fromkeys(lanes, 0), dict.fromkeys(peers, 0)
    batch: dict = {}
    while len(batch) < chunk:
        took = False
        for peer in peers:
            if len(batch) >= chunk:
                break
            order = by_peer[peer]
            for _ in range(len(order)):  # the peer's next client name with a state left
                lane = order[turn[peer] % len(order)]
                turn[peer] += 1
                mine = lists[lane]
                while at[lane] < len(mine) and (mine[at[lane]].setup, mine[at[lane]].record) in batch:
                    at[lane] += 1
                if at[lane] < len(mine):
                    p = mine[at[lane]]
                    batch[(p.setup, p.record)] = p
                    at[lane] += 1
                    served[lane] = served_peer[peer] = round_
                    took = True
                    break
        if not took:
            break
    return batch


def one_line(e: BaseException) -> str:
    return f"{type(e).__name__}: {(str(e).splitlines() or [''])[0][:300]}"


def _annotate(annotator, items: Sequence) -> tuple[int, int]:
    done = rows = 0
    by_setup: dict = {}
    for p in items:
        by_setup.setdefault(p.setup, []).append(p)
    for setup, group in by_setup.items():
        stats = annotator.annotate_states([p.record for p in group], setup.env_id, setup.renderer)
        done, rows = done + stats.annotated_states, rows + stats.rows
    return done, rows


def annotate_batch(annotator, batch: Sequence) -> tuple[int, int, list]:
    """Annotate a batch of `Pending` states (blocking; touches no queue state): what the cache lacks
    of it, one shard per setup; a batch that raises is tried again state by state. Returns (states
    annotated, rows written, [(failed state, one-line reason)])."""
    annotator.cache.refresh()  # trainers and other servers may have written meanwhile
    try:
        done, rows = _annotate(annotator, batch)
        return done, rows, []
    except Exception as e:  # noqa: BLE001 - one state's fault must not cost the others theirs
        if len(batch) == 1:
            return 0, 0, [(batch[0], one_line(e))]
        done = rows = 0
        failed = []
        for p in batch:  # rows written before the fault are in the cache: its keys skip them
            try:
                d, r = _annotate(annotator, [p])
                done, rows = done + d, rows + r
            except Exception as e1:  # noqa: BLE001
                failed.append((p, one_line(e1)))
        return done, rows, failed
    finally:
        hop = getattr(annotator, "_hop", None)  # the annotator's projections: bounded here
        if isinstance(hop, dict) and len(hop) > MAX_HOP_CONTEXTS:
            hop.clear()
        release_free_memory()


def in_thread(work: Callable[[], object], name: str) -> asyncio.Future:
    """`work()` in a daemon thread, as a future of the running loop (settled from the thread)."""
    loop = asyncio.get_running_loop()
    future = loop.create_future()

    def settle(result, error) -> None:
        if not future.done():
            future.set_exception(error) if error is not None else future.set_result(result)

    def run() -> None:
        try:
            result, error = work(), None
        except BaseException as e:  # noqa: BLE001 - handed to the loop
            result, error = None, e
        try:
            loop.call_soon_threadsafe(settle, result, error)
        except RuntimeError:  # the loop is closed: the server stopped past the deadline
            pass

    threading.Thread(target=run, name=name, daemon=True).start()
    return future
