"""The quotas of `illm serve`'s queue: which trainer may be queued, wait, or add states, checked
cheapest first (`intake.Intake`): `check_trainer` before any state of a request is read,
`check_queue` once its states are parsed and before they are measured in tokens, both again when
the request is queued (others may have been meanwhile).

Counted per peer (`config.peer_group`: loopback as one, an IPv4 /24, an IPv6 /64) whatever client
names it sends under: its share of the trainers, of the queue and of the waiting requests
(`--max-peer-share`); per client name from one peer: its sessions (`--max-sessions`) and its share
of the queue (`--max-client-share`), so another peer sending a run's name takes nothing of that
run's; in all: the trainers and the queue (`--max-clients`, `--max-queue`), the last
`--new-peer-room` of both kept for peers with nothing queued, so a few peers cannot fill the server.
A session is tied to the peer of its queued list or waiting request (another peer naming it is
refused); with neither, to the peer of its next request (a dual-stack trainer falling back from
IPv6 to IPv4 goes on).

The checks read the server's queue through its read-only methods (`queued`, `peer_of`,
`is_waiting`, `waiting_from` of `scheduler.AnnotationServer`, named in the annotations as text: it
imports this module, so this one never imports it)."""

from __future__ import annotations

from dataclasses import dataclass, field

from illm_tools.serve.protocol import RequestError
from illm_tools.tasks.annotation_setup import AnnotationSetup

LOOPBACK = "loopback"
"""The peer of every loopback address (`config.peer_group`), and of requests handed in-process."""


@dataclass
class Asked:
    """What is kept of a request once its top-level fields are checked: its trainer, peer, setup and
    wait, and its states until they are parsed (`intake.Intake.parse_states` drops them)."""

    trainer: tuple[str, str]
    peer: str
    setup: AnnotationSetup
    states: list | None
    wait: float
    withdraws: bool = field(init=False)
    """An empty list of states: the trainer withdraws its pending ones."""

    def __post_init__(self) -> None:
        self.withdraws = not self.states


def present(server: AnnotationServer, peer: str, trainer: tuple[str, str]) -> bool:
    """Whether `peer` holds the queue already (a trainer of its own queued, `trainer` included)."""
    return trainer in server.queued() or bool(queued_from(server, peer))


def queued_from(server: AnnotationServer, peer: str) -> list[tuple[str, str]]:
    """The trainers with a list queued from `peer`."""
    return [who for who in server.queued() if server.peer_of(who) == peer]


def check_trainer(server: AnnotationServer, ask: Asked) -> None:
    """RequestError when the request's trainer may not be (or stay) queued or wait: the server
    stopping (503); its session tied to another peer (409); with states, no trainer slot
    left (503), the room kept for new peers (503), its peer's share of the slots (429), its
    client name's sessions from that peer (429); a wait beyond its peer's share (429)."""
    limits, trainer, peer, client = server.limits, ask.trainer, ask.peer, ask.trainer[0]
    if server.stopping:
        raise RequestError(503, "the server is stopping: send the states again when it is back", server.retry_after())
    tied = server.peer_of(trainer)
    if tied is not None and tied != peer:
        raise RequestError(409, f"the session {trainer[1][:40]!r} of {client[:80]!r} has states queued or a request "
                                f"waiting from another peer ({tied}): they are that peer's until annotated or "
                                "withdrawn; a new run makes a new session")
    share = max(1, int(limits.max_peer_share * limits.max_clients))
    if ask.wait and not server.is_waiting(trainer):
        waiting = server.waiting_from(peer)
        if waiting >= share:
            raise RequestError(429, f"the peer {peer} has {waiting} requests waiting, its share of --max-clients "
                                    "(--max-peer-share): wait for fewer at once", server.retry_after())
    queued = server.queued()
    if ask.withdraws or trainer in queued:
        return  # a withdrawal, or a trainer keeping its slot
    if len(queued) >= limits.max_clients:
        raise RequestError(503, f"the server queues the states of {len(queued)} trainers, its limit "
                                "(--max-clients): this run backs off and sends them again", server.retry_after())
    room = int(limits.new_peer_room * limits.max_clients)
    if len(queued) >= limits.max_clients - room and present(server, peer, trainer):
        raise RequestError(503, f"the server's last {room} trainer slots are kept for peers with nothing queued "
                                f"(--new-peer-room), and the peer {peer} has trainers queued: this run backs off",
                           server.retry_after())
    ours = queued_from(server, peer)
    if len(ours) >= share:
        raise RequestError(429, f"the peer {peer} has {len(ours)} trainers queued, its share of --max-clients "
                                "(--max-peer-share)", server.retry_after())
    sessions = sum(1 for who in ours if who[0] == client)
    if sessions >= limits.max_sessions:
        raise RequestError(429, f"the client {client[:80]!r} has {sessions} sessions queued from this peer, the "
                                "server's --max-sessions: one run is one session", server.retry_after())


def check_queue(server: AnnotationServer, ask: Asked, entries: dict) -> None:
    """RequestError (429 or 503, with Retry-After) when queueing `entries` for the trainer (in place
    of its list) would go beyond a queue limit; its current list stays queued. A client name's share
    counts its states from one peer (another peer sending its name takes nothing of it), a peer's
    whatever names it sends under; the last `--new-peer-room` of the queue is for peers with nothing
    queued."""
    if not entries:
        return
    limits, trainer, peer, client = server.limits, ask.trainer, ask.peer, ask.trainer[0]
    queued = server.queued()
    of_peer = [who for who in queued_from(server, peer) if who != trainer]
    others = {k for who, keys in queued.items() if who != trainer for k in keys}
    total = len(others | entries.keys())
    if total > limits.max_queue:
        raise RequestError(503, f"the queue would hold {total:,} states, beyond the server's --max-queue "
                                f"{limits.max_queue:,}: this run backs off and sends them again", server.retry_after())
    room = int(limits.new_peer_room * limits.max_queue)
    if total > limits.max_queue - room and present(server, peer, trainer):
        raise RequestError(503, f"the queue would hold {total:,} states, into the last {room:,} kept for peers "
                                f"with nothing queued (--new-peer-room), and the peer {peer} has states queued: "
                                "this run backs off and sends them again", server.retry_after())
    mine = {k for who in of_peer if who[0] == client for k in queued[who]}
    share = max(1, int(limits.max_client_share * limits.max_queue))
    if len(mine | entries.keys()) > share:
        raise RequestError(429, f"the client {client[:80]!r} would hold {len(mine | entries.keys()):,} queued states, "
                                f"beyond its share {share:,} of the queue (--max-client-share): send fewer",
                           server.retry_after())
    ours = {k for who in of_peer for k in queued[who]}
    share = max(1, int(limits.max_peer_share * limits.max_queue))
    if len(ours | entries.keys()) > share:
        raise RequestError(429, f"the peer {peer} would hold {len(ours | entries.keys()):,} queued states, beyond its "
                                f"share {share:,} of the queue (--max-peer-share): send fewer", server.retry_after())
