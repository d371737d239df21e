"""`ServeConfig`: what `illm serve` loads, where it listens, the annotation setup it writes, and its
limits (`ServeLimits`, each an option, each documented with what exceeding it answers in
docs/commands/serve.md); and the checks of a listening address and of a token's strength."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from illm_tools.annotate.wire import TOKEN_ENV, check_token
from illm_tools.errors import UsageError
from illm_tools.llm.spec import LLMSpec
from illm_tools.tasks.prompt_config import PromptConfig

MIN_TOKEN_BITS = 128
"""Least entropy a server's token must carry (`token_bits`)."""
MAKE_TOKEN = "python -c \"import secrets; print(secrets.token_urlsafe(32))\""


def token_bits(token: str) -> float:
    """A conservative estimate of the bits a token carries: its length times log2 of the alphabet its
    character classes span (hex digits 16; else lower 26, upper 26, digits 10, `-` and `_` 2, other
    punctuation 32), counted as 0 for a token that repeats a shorter piece or uses few distinct
    characters (`aaaa...`, `abab...`), which an attacker tries first."""
    n = len(token)
    if not n or (token + token).find(token, 1) < n or len(set(token)) < max(4, n // 4):
        return 0.0
    if all(c in "0123456789abcdef" for c in token) or all(c in "0123456789ABCDEF" for c in token):
        return n * 4.0
    alphabet = sum(size for test, size in ((str.islower, 26), (str.isupper, 26), (str.isdigit, 10))
                   if any(test(c) for c in token))
    alphabet += 2 if any(c in "-_" for c in token) else 0
    alphabet += 32 if any(not c.isalnum() and c not in "-_" for c in token) else 0
    return n * math.log2(max(alphabet, 2))


def check_token_strength(token: str, option: str = "--token") -> str:
    """`token` when it carries at least MIN_TOKEN_BITS (`token_bits`), else UsageError in one line that
    says how to make one, without repeating the token."""
    check_token(token, option)
    bits = token_bits(token)
    if bits < MIN_TOKEN_BITS:
        raise UsageError(f"{option} (or {TOKEN_ENV}) carries about {bits:.0f} bits, fewer than the {MIN_TOKEN_BITS} a "
                         f"server's token needs (no repeated pieces, few distinct characters or short ones): make one "
                         f"with `{MAKE_TOKEN}`")
    return token


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


def peer_group(address: str) -> str:
    """The group a peer address is counted in for the connection caps: loopback as one (127.0.0.0/8
    and ::1 are this machine), an IPv4 address by its /24, an IPv6 address by its /64 (one host or
    one site takes many addresses there at no cost); anything else (a unix socket) as itself."""
    import ipaddress

    try:
        ip = ipaddress.ip_address(address.split("%")[0])
    except ValueError:
        return address
    if ip.is_loopback or (ip.version == 6 and ip.ipv4_mapped is not None and ip.ipv4_mapped.is_loopback):
        return "loopback"
    if ip.version == 6 and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    prefix = 24 if ip.version == 4 else 64
    return str(ipaddress.ip_network(f"{ip}/{prefix}", strict=False))


MIN_REQUEST_BYTES = 64 * 2**10
"""The smallest --max-request-mb a server takes (64 KiB: one state at every per-field limit)."""


@dataclass
class ServeLimits:
    """What one request, one client and one connection may take of a server. The defaults fit
    `benchmarks/serve_load.py`'s trainers (8 of them, 16 states a rollout, history 0 to 3) many
    times over; what exceeding each answers is in docs/commands/serve.md."""

    max_states: int = 1024
    """States in one request (413 above; a trainer sends at most this many per rollout)."""
    max_request_mb: float = 16.0
    """Request body size in MiB (413 above)."""
    max_text_chars: int = 8192
    """Characters of a mission, an observation or a history observation (413 above)."""
    max_actions: int = 64
    """Valid actions of one state (413 above: a state's cost grows with their number squared)."""
    max_action_chars: int = 64
    """Characters of one valid action (413 above)."""
    max_visits: int = 10**9
    """Largest visit count a state may declare (400 above); visits only order a client's own states."""
    max_clients: int = 64
    """Trainers (client and session) whose states are queued at once; a further one gets 503 with Retry-After."""
    max_sessions: int = 4
    """Sessions (trainers) queued under one client name; a further one gets 429 with Retry-After."""
    max_client_share: float = 0.5
    """Share of --max-queue the states of one client name may hold (429 with Retry-After above)."""
    max_peer_share: float = 0.5
    """Share of --max-queue, and of --max-clients, one peer may hold whatever client names it sends
    under (loopback is one peer, an IPv4 /24 or an IPv6 /64 another; 429 with Retry-After above)."""
    new_peer_room: float = 0.125
    """Share of --max-clients and of --max-queue kept for peers with nothing queued: the peers already
    queued cannot fill it, so a new peer is served however few peers hold the rest (503 with
    Retry-After to a queued peer reaching it; 0: no room kept)."""
    max_queue: int = 8192
    """States queued across all trainers; a request that would go beyond gets 503 with Retry-After
    (the trainer backs off and goes on training)."""
    max_connections: int = 256
    """Open connections in all; a further one is answered 503 and closed."""
    max_connections_per_peer: int = 64
    """Open connections from one peer: loopback as one, an IPv4 /24, an IPv6 /64 (`peer_group`); a
    further one is answered 503 and closed."""
    header_timeout: float = 5.0
    """Seconds a client has to finish a request's headers once it has started them (closed after)."""
    request_timeout: float = 30.0
    """Seconds a client has to send its request's body (408 after, closed); an idle connection is
    closed after as long: a slow or stalled client holds nothing."""
    batch_deadline: float = 600.0
    """Seconds a batch may take in the engine: past it its states are answered as failed, and a stop
    (Ctrl-C, SIGTERM) exits without waiting longer for it."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_numbers

        check_numbers(self, positive=("max_states", "max_request_mb", "max_text_chars", "max_actions",
                                      "max_action_chars", "max_visits", "max_clients", "max_sessions",
                                      "max_client_share", "max_peer_share", "max_queue", "max_connections", "max_connections_per_peer",
                                      "header_timeout", "request_timeout", "batch_deadline"))
        if self.max_request_bytes < MIN_REQUEST_BYTES:
            raise UsageError(f"--max-request-mb {self.max_request_mb:g} cannot hold one state at the per-field limits: "
                             f"give at least {MIN_REQUEST_BYTES / 2**20:g}")
        if self.max_client_share > 1:
            raise UsageError(f"--max-client-share is a share of --max-queue, in (0, 1], got {self.max_client_share:g}")
        if not 0 <= self.new_peer_room < 1:
            raise UsageError(f"--new-peer-room is a share of --max-clients and --max-queue, in [0, 1), got "
                             f"{self.new_peer_room:g}")
        if self.max_peer_share > 1:
            raise UsageError(f"--max-peer-share is a share of --max-queue and --max-clients, in (0, 1], got "
                             f"{self.max_peer_share:g}")

    @property
    def max_request_bytes(self) -> int:
        return int(self.max_request_mb * 2**20)


@dataclass
class ServeConfig:
    """An `illm serve` server: the cache it writes, the LLM it loads, the annotation setup its rows
    carry, where it listens, how it batches, and its limits."""

    cache: Path = Path("data/ann")
    """Annotation cache the answers go to (the trainers' --cache)."""
    llm: LLMSpec = field(default_factory=LLMSpec)
    """The LLM that answers; none of its options given: the cache's one model setup (`adopt_model`)."""
    setup: PromptConfig = field(default_factory=PromptConfig)
    """How states become prompts: the trainers' --history, --layout and, for hop trainers, --hop-seed
    and --hop-beta (a request declaring another is refused, naming the difference; the server answers
    text and hop states alike, so it takes no --mode). Every row the server writes carries its setup."""
    tasks: tuple[str, ...] = ("action", "summary")
    """The language tasks annotated for every state; a trainer may read any of them."""
    port: int = 8765
    """TCP port (0: any free one, printed when ready)."""
    host: str = "127.0.0.1"
    """Address to listen on: loopback by default; any other (0.0.0.0, this machine's cluster address)
    needs a token."""
    token: str | None = field(default=None, repr=False)
    """Token every request must carry (401 without it; trainers pass it with --annotator-token), at
    least 128 bits; default: the ILLM_SERVE_TOKEN environment variable, which keeps it out of
    `ps` and the shell's history. Required to listen beyond loopback. Never printed or logged."""
    batch_size: int = 8
    """States per LLM batch."""
    chunk: int = 16
    """States taken per round across all trainers (round-robin across clients), written as one shard."""
    threads: int = 0
    """Torch threads of the model; 0: every core."""
    limits: ServeLimits = field(default_factory=ServeLimits)
    """What one request, client and connection may take."""

    def __post_init__(self) -> None:
        from illm_tools.settings import check_folder, check_numbers
        from illm_tools.tasks.registry import parse_tasks

        self.cache = Path(self.cache)
        check_numbers(self, positive=("batch_size", "chunk"), non_negative=("threads", "port"))
        if self.port >= 65536:
            raise UsageError(f"--port must be in 0..65535, got {self.port}")
        self.tasks = parse_tasks(self.tasks)
        if self.token is None:
            self.token = os.environ.get(TOKEN_ENV) or None
        if self.token is not None:
            check_token_strength(self.token, "--token")
        elif not is_loopback(self.host):
            raise UsageError(f"--host {self.host or '(every address)'} listens beyond this machine, where anyone could "
                             f"send states: give the server a token (--token, or the {TOKEN_ENV} environment variable) "
                             "and pass it to every trainer (--annotator-token, or the same variable)")
        check_folder(self.cache, "--cache")
