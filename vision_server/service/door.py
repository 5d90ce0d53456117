"""The front door: what every front-end's connections and sign-ins go through.

Each listener (the binary protocol, the web console, the line protocol, Modbus) asks the door
before it serves a connection, and gives the pass back when the connection ends:

- **Connection admission.** A connection is counted against its front-end's own limit and
  against one limit for the whole server (``server: max_connections_total``), so that no
  front-end, however many clients it has, can take the file descriptors every other one
  needs. Front-ends count a connection when it is accepted: before TLS and before any
  authentication.
- **Failed authentication is slowed down.** After a wrong token the front-end waits
  :meth:`FrontDoor.auth_failed`'s delay before it answers: doubling per failure from the same
  host (an IPv6 /64, all of loopback as one; ``AUTH_DELAY_MIN_S`` to ``AUTH_DELAY_MAX_S``), the
  longest for every failure while more than ``BUSY_FAILURES`` a minute come from anywhere
  (many addresses guess as one), forgotten after ``AUTH_MEMORY_S`` without
  one. A right token is never delayed, and does not reset its host's count (a guesser behind
  the same address as a robot gains nothing from the robot's sign-ins). Guessing a token then
  takes years instead of hours; a person who mistyped waits a moment.

The door does no I/O and holds no connection: it is bookkeeping on the event loop (no locks),
so that every front-end keeps the same rules without implementing them.
"""

from __future__ import annotations

import ipaddress
import resource
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass

DESCRIPTORS_KEPT = 128
"""File descriptors left over for what is not a connection (the result log, cameras, the
worker processes' pipes, files read for a reload): the total limit never goes above the
process's descriptor limit less these."""
AUTH_DELAY_MIN_S = 0.1
AUTH_DELAY_MAX_S = 5.0
AUTH_MEMORY_S = 600.0
"""A host whose last failure is older than this starts again at the shortest delay."""
MAX_HOSTS_REMEMBERED = 4096
"""Failing hosts kept; the one that failed longest ago is forgotten beyond (bounded memory)."""
BUSY_FAILURES = 30
"""More failed sign-ins than this within ``BUSY_WINDOW_S``, from anywhere, and every failure
waits the longest delay: a guesser with many addresses is slowed down as one."""
BUSY_WINDOW_S = 60.0


def descriptor_limit() -> int:
    """The process's soft limit of open file descriptors (a large number where unlimited)."""
    soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    return soft if soft != resource.RLIM_INFINITY else 1 << 20


@dataclass
class Pass:
    """One admitted connection. :meth:`leave` gives its place back (once; later calls do
    nothing), whatever way the connection ended."""

    frontend: str
    peer: str
    _door: FrontDoor
    _left: bool = False

    def leave(self) -> None:
        if not self._left:
            self._left = True
            self._door._leave(self.frontend)


@dataclass(frozen=True)
class Refusal:
    """Why a connection was not admitted, in words for a log line or a refusal message."""

    reason: str


class FrontDoor:
    """Connection counts and sign-in failures for every front-end of one server.

    ``total`` is the most connections the server holds at once over all its front-ends; it is
    lowered to the descriptor limit less :data:`DESCRIPTORS_KEPT` when that is smaller.
    """

    def __init__(self, total: int, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.total = max(1, min(total, descriptor_limit() - DESCRIPTORS_KEPT))
        self._clock = clock
        self._open: dict[str, int] = {}
        self._refused: dict[str, int] = {}
        self._failures: OrderedDict[str, tuple[int, float]] = OrderedDict()
        self._recent: deque[float] = deque(maxlen=BUSY_FAILURES + 1)

    # ------------------------------------------------------------------ connections

    def enter(self, frontend: str, peer: str, *, limit: int) -> Pass | Refusal:
        """Admit a connection of ``frontend`` (which holds at most ``limit`` at once), or say
        why not. Call it as the connection is accepted, before TLS."""
        held = self._open.get(frontend, 0)
        if held >= limit:
            return self._refuse(frontend, f"too many connections to the {frontend} ({limit})")
        if self.connections >= self.total:
            return self._refuse(
                frontend, f"too many connections to the server ({self.total} in all)"
            )
        self._open[frontend] = held + 1
        return Pass(frontend, peer, self)

    @property
    def connections(self) -> int:
        """Connections held now, over every front-end."""
        return sum(self._open.values())

    def held(self, frontend: str) -> int:
        return self._open.get(frontend, 0)

    def counts(self) -> dict[str, dict[str, int]]:
        """Per front-end: connections held now and refused since the start."""
        names = sorted(set(self._open) | set(self._refused))
        return {
            name: {"open": self._open.get(name, 0), "refused": self._refused.get(name, 0)}
            for name in names
        }

    def _refuse(self, frontend: str, reason: str) -> Refusal:
        self._refused[frontend] = self._refused.get(frontend, 0) + 1
        return Refusal(reason)

    def _leave(self, frontend: str) -> None:
        self._open[frontend] -= 1

    # ------------------------------------------------------------------ sign-in

    def auth_failed(self, peer: str) -> float:
        """Record a wrong token from ``peer`` (an address, with or without its port); returns
        how long, in seconds, the front-end waits before it answers."""
        host = failure_key(peer_host(peer))
        now = self._clock()
        count, last = self._failures.pop(host, (0, now))
        if now - last > AUTH_MEMORY_S:
            count = 0
        count += 1
        self._failures[host] = (count, now)
        while len(self._failures) > MAX_HOSTS_REMEMBERED:
            self._failures.popitem(last=False)
        self._recent.append(now)
        if len(self._recent) > BUSY_FAILURES and now - self._recent[0] <= BUSY_WINDOW_S:
            return AUTH_DELAY_MAX_S
        return float(min(AUTH_DELAY_MIN_S * 2.0 ** min(count - 1, 32), AUTH_DELAY_MAX_S))

    def failing_hosts(self) -> int:
        return len(self._failures)


def peer_name(address: object) -> str:
    """``host:port`` (``[v6]:port``) of a socket's peer address, as logs and the door name it."""
    if isinstance(address, tuple) and len(address) >= 2:
        host, port = address[0], address[1]
        return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    return str(address)


def failure_key(host: str) -> str:
    """Whose failures count together: an IPv6 address's /64 (one site's, however many
    addresses it uses), every loopback address as one, else the IPv4 address."""
    try:
        address = ipaddress.ip_address(host.split("%", 1)[0])
    except ValueError:
        return host
    if address.is_loopback:
        return "loopback"
    if isinstance(address, ipaddress.IPv6Address):
        if address.ipv4_mapped is not None:
            return failure_key(str(address.ipv4_mapped))
        return str(ipaddress.IPv6Network((address, 64), strict=False))
    return str(address)


def peer_host(peer: str) -> str:
    """The host part of ``host:port`` or ``[v6]:port`` (the port changes per connection, and a
    guesser would open a new connection per guess)."""
    if peer.startswith("["):
        return peer[1 : peer.find("]")] if "]" in peer else peer
    if peer.count(":") == 1:
        return peer.rsplit(":", 1)[0]
    return peer


__all__ = [
    "AUTH_DELAY_MAX_S",
    "AUTH_DELAY_MIN_S",
    "DESCRIPTORS_KEPT",
    "FrontDoor",
    "Pass",
    "Refusal",
    "descriptor_limit",
    "failure_key",
    "peer_host",
    "peer_name",
]
