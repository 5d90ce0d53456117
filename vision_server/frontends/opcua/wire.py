"""asyncua's per-connection protocol behind the front door's rules.

The listener (:class:`~vision_server.frontends.listener.Listener`) counts the connection before
anything is read and closes it when its clock runs out; this wrapper gives the clock what only
the byte stream shows, before asyncua sees a byte:

- every OPC UA chunk header (message type, chunk type, size) is checked as it arrives: an
  unknown message type or a chunk larger than the receive buffer the server offers closes the
  connection at once, so no client holds more than one chunk of unparsed bytes (asyncua itself
  would buffer whatever a header claims); until its session is activated a connection sends
  single-chunk messages only, at most two OpenSecureChannel messages of at most 16 KiB (each is
  decrypted with the server's private key before anything can look at it);
- each complete chunk is a sign of life: the clock's deadline moves on, to the request timeout
  until a session is activated (:data:`~.access.SIGNED_IN`), to the idle timeout after;
- a client that sends requests faster than asyncua answers them is read no further while
  ``max_waiting`` of its chunks wait (TCP pushes back on it), instead of being dropped as
  asyncua does when its queue fills (asyncua's own client sends dozens at once);
- the connection's peer is put in :data:`~.access.PEER` before asyncua starts the task that
  processes its messages, so that its sign-ins know where they come from.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any

from ...service import peer_name
from ..listener import Clock, Policy
from .access import PEER, SIGNED_IN

log = logging.getLogger("vision_server")

HEADER_BYTES = 8
MESSAGE_TYPES = frozenset({b"HEL", b"ACK", b"ERR", b"RHE", b"OPN", b"MSG", b"CLO"})
CHUNK_TYPES = frozenset(b"FCA")
MAX_OPEN_BYTES = 16 * 1024
"""An OpenSecureChannel message is a certificate or two and a nonce: a few KiB. Each of its
RSA blocks costs the server a private-key operation, so a large one is refused unread."""
MAX_OPENS_BEFORE_SIGN_IN = 2
"""OpenSecureChannel messages a connection may send before its session is activated (a
channel's opening, and one retry); renewals come later, when it is signed in."""
RESUME_CHECK_S = 0.005
"""How soon a paused connection looks again whether asyncua has taken its waiting chunks."""


class Guarded(asyncio.Protocol):
    """``inner`` (asyncua's OPCUAProtocol) with its chunks checked (see the module)."""

    def __init__(
        self,
        inner: Any,
        *,
        policy: Policy,
        max_chunk_bytes: int,
        max_waiting: int,
        clock_of: Callable[[asyncio.BaseTransport | None], Clock | None],
        on_processor: Callable[[Any, str], None] | None = None,
    ) -> None:
        self.inner = inner
        self.policy = policy
        self.max_chunk_bytes = max_chunk_bytes
        self.max_waiting = max_waiting
        self._paused = False
        self.clock_of = clock_of
        self.on_processor = on_processor
        """Called with asyncua's message processor of the connection once it is made (the
        front-end hardens it: :mod:`.hardening`)."""
        self.transport: asyncio.Transport | None = None
        self.peer = ""
        self._head = b""
        self._left = 0
        self._closed = False
        self._opens = 0

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        self.peer = peer_name(transport.get_extra_info("peername"))
        PEER.set(self.peer)  # copied into the task asyncua starts next (see the module)
        SIGNED_IN.set(self._signed_in)
        self.inner.connection_made(transport)
        processor = getattr(self.inner, "processor", None)
        if processor is not None and self.on_processor is not None:
            self.on_processor(processor, self.peer)

    def connection_lost(self, exc: Exception | None) -> None:
        self._closed = True
        self.inner.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._closed:
            return
        problem = self._scan(data)
        if problem is not None:
            self._closed = True
            log.info("OPC UA: closing the connection from %s: %s", self.peer, problem)
            if self.transport is not None:
                self.transport.abort()
            return
        self.inner.data_received(data)
        if not self._paused and self._waiting() >= self.max_waiting and self.transport:
            self._paused = True
            self.transport.pause_reading()
            asyncio.get_running_loop().call_later(RESUME_CHECK_S, self._resume_when_drained)

    def _waiting(self) -> int:
        queue = getattr(self.inner, "messages", None)
        return queue.qsize() if isinstance(queue, asyncio.Queue) else 0

    def _resume_when_drained(self) -> None:
        if self._closed or self.transport is None or self.transport.is_closing():
            return
        if self._waiting() > self.max_waiting // 2:
            asyncio.get_running_loop().call_later(RESUME_CHECK_S, self._resume_when_drained)
            return
        self._paused = False
        self.transport.resume_reading()

    def eof_received(self) -> bool | None:
        return None  # asyncua has nothing to say after the client's end: close

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()

    # ------------------------------------------------------------------ chunks

    def _scan(self, data: bytes) -> str | None:
        """Follow the chunk boundaries through ``data``; the reason to close, or None."""
        at, size = 0, len(data)
        while at < size:
            if self._left == 0:
                take = min(HEADER_BYTES - len(self._head), size - at)
                self._head += data[at : at + take]
                at += take
                if len(self._head) < HEADER_BYTES:
                    return None
                kind, chunk = self._head[:3], self._head[3]
                length = int.from_bytes(self._head[4:8], "little")
                self._head = b""
                if kind not in MESSAGE_TYPES or chunk not in CHUNK_TYPES:
                    return f"not OPC UA binary (a chunk of type {kind!r}/{chunk:#04x})"
                if not HEADER_BYTES <= length <= self.max_chunk_bytes:
                    return (
                        f"a chunk of {length} bytes (at most {self.max_chunk_bytes}, the receive "
                        "buffer the server offers)"
                    )
                problem = self._before_sign_in(kind, chunk, length)
                if problem is not None:
                    return problem
                self._left = length - HEADER_BYTES
                if self._left == 0:
                    self._chunk_done()
            else:
                take = min(self._left, size - at)
                self._left -= take
                at += take
                if self._left == 0:
                    self._chunk_done()
        return None

    def _before_sign_in(self, kind: bytes, chunk: int, length: int) -> str | None:
        """What a connection may not send before its session is activated: asyncua decodes
        (and for OpenSecureChannel, RSA-decrypts) a whole message before anything can look at
        it, so a stranger's messages are kept to one chunk, and its channel opening small and
        rare."""
        if kind == b"OPN":
            self._opens += 1
            if length > MAX_OPEN_BYTES:
                return f"an OpenSecureChannel of {length} bytes (at most {MAX_OPEN_BYTES})"
        clock = self.clock_of(self.transport)
        if clock is not None and clock.signed_in:
            return None
        if kind == b"OPN" and self._opens > MAX_OPENS_BEFORE_SIGN_IN:
            return "OpenSecureChannel again before signing in"
        if chunk == ord("C"):
            return "a message of several chunks before signing in"
        return None

    def _chunk_done(self) -> None:
        clock = self.clock_of(self.transport)
        if clock is not None:
            clock.begin()
            clock.end(self.policy, time.monotonic())

    def _signed_in(self) -> None:
        """A session of this connection was activated: idle timeouts from now on."""
        clock = self.clock_of(self.transport)
        if clock is not None:
            clock.signed_in = True
            clock.deadline = time.monotonic() + self.policy.idle_timeout_s


__all__ = ["Guarded", "MESSAGE_TYPES"]
