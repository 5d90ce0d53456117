"""The sans-IO connection: bytes in, messages out; messages in, bytes out.

Like h11, it does no I/O. Feed received bytes with :meth:`Connection.receive_data` (``b""`` for
end of stream), take events with :meth:`Connection.next_event` until it returns ``NEED_DATA`` (or
``PAUSED``, when the server's own admission defers a frame: stop reading, as h11's PAUSED), and
turn outgoing messages into bytes with :meth:`Connection.send`.

Everything that affects the state machine lives in this file, in ``TRANSITIONS``.
"""

from __future__ import annotations

from collections.abc import KeysView
from dataclasses import dataclass
from enum import Enum
from typing import Any

from .constants import NO_REQUEST, SUPPORTED_VERSIONS, MessageType
from .errors import (
    CellvisionError,
    DuplicateRequestId,
    FrameTooLarge,
    LocalProtocolError,
    MalformedFrame,
    NotAuthenticated,
    TooLargeToSend,
    UnexpectedMessage,
    UnknownMessageType,
    UnsupportedVersion,
)
from .frames import AdmitCheck, AdmitLater, Blob, FrameDecoder, Header, HeaderCheck, Limits
from .messages import DecodeContext, Error, Message, Version, Welcome, message_from_frame


class Role(Enum):
    CLIENT = "client"
    SERVER = "server"


class State(Enum):
    """The state of one connection, seen from one side."""

    HANDSHAKE = "handshake"
    """Client: HELLO not yet sent or WELCOME not yet received. Server: waiting for HELLO."""
    HELLO_RECEIVED = "hello_received"
    """Server only: HELLO received, WELCOME (or a fatal ERROR) not yet sent."""
    OPEN = "open"
    CLOSING = "closing"
    """Client: it sent CLOSE and waits for the server's CLOSE. Server: the client sent CLOSE;
    the server answers what is in flight, then sends CLOSE."""
    CLOSED = "closed"


class Direction(Enum):
    SEND = "send"
    RECEIVE = "receive"


class _NeedData:
    def __repr__(self) -> str:
        return "NEED_DATA"


NEED_DATA = _NeedData()
"""Returned by next_event when a whole frame has not arrived yet."""


class _Paused:
    def __repr__(self) -> str:
        return "PAUSED"


PAUSED = _Paused()
"""Returned by next_event when the owner's ``admit`` deferred the next frame
(:class:`~protocol.frames.AdmitLater`): stop reading from the peer until the frame can be
admitted (TCP backpressure), then call next_event again, which asks ``admit`` again."""


@dataclass(frozen=True)
class ConnectionClosed:
    """Returned by next_event once the peer closed the stream cleanly between frames."""


S, R = Direction.SEND, Direction.RECEIVE
C, V = Role.CLIENT, Role.SERVER
T = MessageType

REQUESTS = frozenset(
    {T.HELLO, T.PING, T.LIST_INSPECTIONS, T.INSPECT, T.CAPTURE, T.RELOAD, T.OPERATOR_CALL}
)
"""Client → server messages that are answered by a response with the same request id."""

RESPONSES: dict[MessageType, frozenset[MessageType]] = {
    T.HELLO: frozenset({T.WELCOME, T.ERROR}),
    T.PING: frozenset({T.PONG, T.ERROR}),
    T.LIST_INSPECTIONS: frozenset({T.INSPECTIONS, T.ERROR}),
    T.INSPECT: frozenset({T.RESULT, T.ERROR}),
    T.CAPTURE: frozenset({T.FRAMES, T.ERROR}),
    T.RELOAD: frozenset({T.RELOADED, T.ERROR}),
    T.OPERATOR_CALL: frozenset({T.OPERATOR_ANSWER, T.ERROR}),
}
"""The message types that may answer each request type."""

_OPEN_REQUESTS = (T.PING, T.LIST_INSPECTIONS, T.INSPECT, T.CAPTURE, T.RELOAD, T.OPERATOR_CALL)
_OPEN_RESPONSES = (
    T.PONG,
    T.INSPECTIONS,
    T.RESULT,
    T.FRAMES,
    T.RELOADED,
    T.OPERATOR_ANSWER,
    T.ERROR,
)

INTRODUCED_IN: dict[MessageType, Version] = {
    T.OPERATOR_CALL: (1, 1),
    T.OPERATOR_ANSWER: (1, 1),
}
"""Message types a minor version added, with that version; the others are 1.0's. On a
connection that agreed on an older minor they are unknown types (SPEC §8.2): a peer refuses
them as UNKNOWN_MESSAGE_TYPE, and this side will not send them."""

_SERVER_LIVE_STATES = (State.HANDSHAKE, State.HELLO_RECEIVED, State.OPEN, State.CLOSING)

TRANSITIONS: dict[tuple[Role, State, Direction, MessageType], State] = {
    # client handshake
    (C, State.HANDSHAKE, S, T.HELLO): State.HANDSHAKE,
    (C, State.HANDSHAKE, R, T.WELCOME): State.OPEN,
    (C, State.HANDSHAKE, R, T.ERROR): State.HANDSHAKE,
    # server handshake
    (V, State.HANDSHAKE, R, T.HELLO): State.HELLO_RECEIVED,
    (V, State.HELLO_RECEIVED, S, T.WELCOME): State.OPEN,
    # a non-fatal ERROR answering HELLO (BUSY, ...): the client may send another HELLO
    (V, State.HELLO_RECEIVED, S, T.ERROR): State.HANDSHAKE,
    (V, State.HANDSHAKE, S, T.ERROR): State.HANDSHAKE,
    # open: requests one way, responses the other
    **{(C, State.OPEN, S, t): State.OPEN for t in _OPEN_REQUESTS},
    **{(V, State.OPEN, R, t): State.OPEN for t in _OPEN_REQUESTS},
    **{(C, State.OPEN, R, t): State.OPEN for t in _OPEN_RESPONSES},
    **{(V, State.OPEN, S, t): State.OPEN for t in _OPEN_RESPONSES},
    # graceful close started by the client: the server still answers what is in flight
    (C, State.OPEN, S, T.CLOSE): State.CLOSING,
    (V, State.OPEN, R, T.CLOSE): State.CLOSING,
    **{(C, State.CLOSING, R, t): State.CLOSING for t in _OPEN_RESPONSES},
    **{(V, State.CLOSING, S, t): State.CLOSING for t in _OPEN_RESPONSES},
    (C, State.CLOSING, R, T.CLOSE): State.CLOSED,
    (V, State.CLOSING, S, T.CLOSE): State.CLOSED,
    # close started by the server (shutdown): nothing more comes from it
    (V, State.OPEN, S, T.CLOSE): State.CLOSED,
    (C, State.OPEN, R, T.CLOSE): State.CLOSED,
    (C, State.HANDSHAKE, R, T.CLOSE): State.CLOSED,
    (V, State.HANDSHAKE, S, T.CLOSE): State.CLOSED,
    (V, State.HELLO_RECEIVED, S, T.CLOSE): State.CLOSED,
    # a client's fatal ERROR (SPEC §7): the connection is over, in any state
    **{(V, state, R, T.ERROR): State.CLOSED for state in _SERVER_LIVE_STATES},
}
"""(role, state, direction, message type) → next state. A pair not listed is not allowed.

After any fatal ERROR (sent or received) the state becomes CLOSED, whatever the table says.
"""


class Connection:
    """One side of one protocol connection, with no I/O.

    ``limits`` bound what is accepted from the peer. ``versions`` are the (major, minor)
    versions this side speaks, newest first.
    """

    def __init__(
        self,
        role: Role,
        *,
        limits: Limits | None = None,
        versions: tuple[Version, ...] = SUPPORTED_VERSIONS,
        check_header: HeaderCheck | None = None,
        admit: AdmitCheck | None = None,
    ) -> None:
        """Server side, the owner's admission, before a frame's body is buffered:
        ``check_header`` is called with the header of every frame that the state machine
        accepts (it may refuse it on its size alone, before any body byte has arrived);
        ``admit`` then with the header and the frame's metadata (what it asks for), before its
        blobs arrive. Either raises a CellvisionError to refuse the frame (e.g. BUSY: the body
        is then skipped, not kept in memory); ``admit`` may raise
        :class:`~protocol.frames.AdmitLater` to defer it (next_event returns :data:`PAUSED`)."""
        self.role = role
        self.limits = limits or Limits()
        self.versions = tuple(sorted(versions, reverse=True))
        self.state = State.HANDSHAKE
        self.version: Version | None = None
        self._decoder = FrameDecoder(self.limits)
        self._decoder.check_header = self._check_header
        self._owner_check_header = check_header
        self._admit = admit
        if admit is not None:
            self._decoder.admit = self._admit_frame
        self._refused_at_header = False
        self._ctx = DecodeContext(max_image_pixels=self.limits.max_image_pixels)
        # request id -> request type: ids the client sent and awaits, or the server owes.
        self._pending: dict[int, MessageType] = {}
        self._closed_cleanly = False
        # The fatal error that closed the connection on receipt; next_event raises it again.
        self._fatal: CellvisionError | None = None

    # ------------------------------------------------------------------ introspection

    @property
    def pending(self) -> KeysView[int]:
        """Request ids awaiting an answer (client) or owed an answer (server): a live,
        read-only view (no copy per request; ``sorted()`` it to keep a snapshot)."""
        return self._pending.keys()

    def speaks(self, version: Version) -> bool:
        """True when this side speaks ``version`` (same major, minor not above ours)."""
        return any(version[0] == major and version[1] <= minor for major, minor in self.versions)

    @property
    def receiving_frame(self) -> bool:
        """True while part of a frame has arrived and the rest has not (also a skipped body)."""
        return self._decoder.in_frame

    @property
    def wire_version(self) -> Version:
        """The version written in outgoing headers: the negotiated one, else our newest."""
        return self.version or self.versions[0]

    # ------------------------------------------------------------------ receiving

    def receive_data(self, data: Blob) -> None:
        """Feed bytes from the peer; ``b""`` means the peer closed its sending side.

        ``data`` (any bytes-like object) is copied at once, never kept. To receive without
        that copy, read into :meth:`get_buffer` and call :meth:`buffer_updated`.
        """
        self._decoder.feed(data)

    def get_buffer(self) -> memoryview:
        """A writable buffer for the next bytes from the peer (asyncio ``BufferedProtocol``,
        ``socket.recv_into``): the rest of the frame body being received, so that an image's
        bytes land where the message will view them. Then call :meth:`buffer_updated`."""
        return self._decoder.get_buffer()

    def buffer_updated(self, nbytes: int) -> None:
        """``nbytes`` (> 0) were received into the latest :meth:`get_buffer` view."""
        self._decoder.buffer_updated(nbytes)

    @property
    def buffered_bytes(self) -> int:
        """Bytes received and held, not yet returned as messages (a skipped body is not
        held): what this connection costs in memory now."""
        return self._decoder.buffered

    @property
    def copied_bytes(self) -> int:
        """Received body bytes that were copied on their way into a frame body (0 when all
        arrived through :meth:`get_buffer`); for tests and benchmarks that count copies."""
        return self._decoder.copied_bytes

    def next_event(self) -> Message | _NeedData | _Paused | ConnectionClosed:
        """The next message from the peer, ``NEED_DATA``, ``PAUSED`` (the owner's ``admit``
        deferred the next frame), or ``ConnectionClosed``.

        Raises a :class:`~protocol.errors.CellvisionError` subclass when the peer broke the
        protocol. When the error is not fatal, its frame has been consumed and the connection
        goes on; a server answers it with an ERROR carrying the error's request id, and a client
        fails its request of that id (no longer pending). When it is fatal, the state is CLOSED:
        answer with an ERROR (``send`` allows it) and close; later calls raise it again.
        """
        if self.state is State.CLOSED:
            # Nothing is read after the connection closed, however it closed.
            if self._fatal is not None:
                raise self._fatal
            return ConnectionClosed()
        self._refused_at_header = False
        try:
            frame = self._decoder.next_frame()
        except CellvisionError as exc:
            header = self._decoder.last_header
            if not exc.fatal and header is not None and not self._refused_at_header:
                # Bad metadata JSON (the frame is consumed): the header still goes through the
                # state machine first, so a bad frame before HELLO is NOT_AUTHENTICATED, etc.
                try:
                    self._check_frame(header.type, (header.major, header.minor), header.request_id)
                except CellvisionError as first:
                    self._on_error(first)
                    raise first from None
            self._on_error(exc)
            raise
        if frame is None:
            if self._decoder.paused:
                return PAUSED
            if self._decoder.eof:
                if self._pending and self.role is Role.CLIENT:
                    lost = MalformedFrame(
                        f"the server closed the connection with {len(self._pending)} "
                        "requests unanswered"
                    )
                    self._close_with(lost)
                    raise lost
                self.state = State.CLOSED
                self._closed_cleanly = True
                return ConnectionClosed()
            return NEED_DATA
        try:
            key = self._check_frame(frame.type, frame.version, frame.request_id)
            message = message_from_frame(frame, self._ctx)
            if self.role is Role.SERVER and isinstance(message, Error) and not message.fatal:
                # A client may only end the connection with an ERROR (SPEC §7), not answer.
                self._reject_unexpected(T.ERROR, frame.request_id, why="a non-fatal ERROR")
            self._apply(key, message)
        except CellvisionError as exc:
            self._on_error(exc)
            raise
        return message

    def _check_header(self, header: Header) -> None:
        """The decoder's header hook: the state machine and the owner's admission, before the
        body is read (SPEC §3.1: no memory for a body that will be refused)."""
        try:
            self._check_frame(header.type, (header.major, header.minor), header.request_id)
            limit = self.limits.max_handshake_frame_bytes
            handshaking = self.state in (State.HANDSHAKE, State.HELLO_RECEIVED)
            if self.role is Role.SERVER and handshaking and header.frame_length > limit:
                # SPEC §3.4: before the handshake only a HELLO-sized frame is buffered.
                raise FrameTooLarge(
                    f"frame of {header.frame_length} bytes before the handshake completed; "
                    f"the limit until WELCOME is {limit} bytes",
                    request_id=header.request_id,
                    details={"size": header.frame_length, "max_size": limit},
                )
            if self._owner_check_header is not None:
                self._owner_check_header(header)
        except CellvisionError:
            self._refused_at_header = True
            raise

    def _admit_frame(self, header: Header, metadata: dict[str, Any]) -> None:
        """The decoder's admission hook: the owner's ``admit``, with the frame's metadata."""
        assert self._admit is not None
        try:
            self._admit(header, metadata)
        except AdmitLater:
            raise
        except CellvisionError:
            self._refused_at_header = True
            raise

    def _on_error(self, exc: CellvisionError) -> None:
        if exc.fatal:
            self._close_with(exc)
        elif exc.request_id != NO_REQUEST:
            if self.role is Role.SERVER:
                # The server owes an ERROR for this request id.
                self._pending.setdefault(exc.request_id, MessageType.ERROR)
            else:
                # The client's request got an answer it cannot use: it is over, and the
                # caller fails it with this error.
                self._pending.pop(exc.request_id, None)

    def _close_with(self, exc: CellvisionError) -> None:
        self.state = State.CLOSED
        self._fatal = exc

    def _check_frame(
        self, raw_type: int, version: Version, rid: int
    ) -> tuple[Role, State, Direction, MessageType]:
        """Check a frame's header against the state machine; the transition key if allowed."""
        try:
            mtype = MessageType(raw_type)
        except ValueError:
            if self.role is Role.SERVER and self.state in (State.HANDSHAKE, State.HELLO_RECEIVED):
                raise NotAuthenticated(
                    f"message type 0x{raw_type:04x} before the handshake completed",
                    request_id=rid,
                ) from None
            raise UnknownMessageType(
                f"unknown message type 0x{raw_type:04x}", request_id=rid
            ) from None
        self._check_version(mtype, version, rid)
        if not self._agreed_on(mtype):
            raise UnknownMessageType(
                f"message type 0x{raw_type:04x} ({mtype.name}) belongs to version "
                f"{_dotted(INTRODUCED_IN[mtype])}; this connection agreed on "
                f"{_dotted(self.version or self.wire_version)}",
                request_id=rid,
            )
        key = (self.role, self.state, Direction.RECEIVE, mtype)
        if key not in TRANSITIONS:
            self._reject_unexpected(mtype, rid)
        if self.role is Role.SERVER and mtype in REQUESTS and rid == NO_REQUEST:
            raise UnexpectedMessage(
                f"{mtype.name} with request id 0, which is reserved for connection-level messages"
            )
        if self.role is Role.SERVER and mtype in REQUESTS and rid in self._pending:
            raise DuplicateRequestId(
                f"request id {rid} is already in flight on this connection", request_id=rid
            )
        if self.role is Role.CLIENT and mtype not in REQUESTS and mtype is not T.CLOSE:
            self._match_response(mtype, rid)
        return key

    def _agreed_on(self, mtype: MessageType) -> bool:
        """Whether ``mtype`` exists in the version this connection agreed on (before the
        handshake: nothing beyond HELLO is allowed anyway, the state machine says so)."""
        introduced = INTRODUCED_IN.get(mtype)
        if introduced is None or self.version is None:
            return True
        return self.version[0] != introduced[0] or self.version[1] >= introduced[1]

    def _check_version(self, mtype: MessageType, version: Version, rid: int) -> None:
        if mtype in (T.HELLO, T.ERROR) or self.version is None:
            # HELLO comes before a version is agreed; an ERROR may answer a failed handshake.
            return
        if version[0] != self.version[0]:
            raise UnsupportedVersion(
                f"frame of version {version[0]}.{version[1]} on a connection that agreed on "
                f"{self.version[0]}.{self.version[1]}",
                request_id=rid,
            )

    def _reject_unexpected(self, mtype: MessageType, rid: int, *, why: str = "") -> None:
        if self.role is Role.SERVER and self.state in (State.HANDSHAKE, State.HELLO_RECEIVED):
            raise NotAuthenticated(
                f"{why or mtype.name} before the handshake completed: HELLO, then wait for WELCOME",
                request_id=rid,
            )
        if why:
            raise UnexpectedMessage(
                f"{why} from the client: a client sends ERROR only to end the connection "
                "(fatal: true)",
                request_id=rid,
            )
        if self.state in (State.HANDSHAKE, State.HELLO_RECEIVED):
            raise UnexpectedMessage(f"{mtype.name} during the handshake", request_id=rid)
        raise UnexpectedMessage(
            f"{mtype.name} is not allowed from the {'client' if self.role is V else 'server'} "
            f"in state {self.state.value}",
            request_id=rid,
        )

    def _match_response(self, mtype: MessageType, rid: int) -> None:
        if mtype is T.ERROR and rid == NO_REQUEST:
            return
        request = self._pending.get(rid)
        if request is None:
            raise UnexpectedMessage(
                f"{mtype.name} for request id {rid}, which is not in flight", request_id=rid
            )
        if mtype not in RESPONSES[request]:
            raise UnexpectedMessage(
                f"{mtype.name} cannot answer {request.name} (id {rid})", request_id=rid
            )

    # ------------------------------------------------------------------ sending

    def send(self, message: Message) -> bytes:
        """The bytes of ``message``; raises LocalProtocolError if it may not be sent now."""
        return b"".join(self.send_parts(message))

    def send_parts(self, message: Message, *, max_bytes: int | None = None) -> list[Blob]:
        """Like :meth:`send`, the frame as buffers to write in order (``writelines``,
        ``socket.sendmsg``): the image blobs are not copied into one ``bytes``.

        ``max_bytes``: raise :class:`TooLargeToSend` for a larger frame. Whatever is raised
        (also TypeError or ValueError for metadata JSON cannot carry) leaves the state as
        it was: nothing was sent."""
        mtype = message.TYPE
        key = (self.role, self.state, Direction.SEND, mtype)
        # A fatal ERROR may still be sent after the peer broke the protocol.
        late_error = mtype is T.ERROR and self.state is State.CLOSED and not self._closed_cleanly
        if key not in TRANSITIONS and not late_error:
            raise LocalProtocolError(
                f"cannot send {mtype.name} as {self.role.value} in state {self.state.value}"
            )
        if not self._agreed_on(mtype):
            raise LocalProtocolError(
                f"{mtype.name} belongs to version {_dotted(INTRODUCED_IN[mtype])}; this "
                f"connection agreed on {_dotted(self.wire_version)}"
            )
        rid = message.request_id
        if mtype is T.CLOSE and rid != NO_REQUEST:
            raise LocalProtocolError("CLOSE must carry request id 0")
        if self.role is Role.CLIENT and mtype in REQUESTS:
            if rid == NO_REQUEST:
                raise LocalProtocolError("request id 0 is reserved for connection-level messages")
            if rid in self._pending:
                raise LocalProtocolError(f"request id {rid} is already in flight")
        if (
            self.role is Role.SERVER
            and mtype is not T.CLOSE
            and not (mtype is T.ERROR and (rid == NO_REQUEST or late_error))
        ):
            request = self._pending.get(rid)
            if request is None:
                raise LocalProtocolError(f"no request with id {rid} is waiting for an answer")
            if request is not T.ERROR and mtype not in RESPONSES[request]:
                raise LocalProtocolError(f"{mtype.name} cannot answer {request.name}")
        version = self.wire_version
        if isinstance(message, Welcome):
            if not self.speaks(message.version):
                raise LocalProtocolError(f"version {message.version} is not one we speak")
            version = message.version  # the WELCOME goes out in the version it chose
        data = message.to_frame(version).serialize_parts()
        if max_bytes is not None:
            size = sum(len(part) for part in data)
            if size > max_bytes:
                raise TooLargeToSend(
                    f"{mtype.name} is {size} bytes, more than the {max_bytes} the peer accepts",
                    size,
                    max_bytes,
                )
        if isinstance(message, Welcome):
            self.version = message.version  # only once it is sent
        if key in TRANSITIONS:
            self._apply(key, message)
        return data

    # ------------------------------------------------------------------ shared bookkeeping

    def _apply(self, key: tuple[Role, State, Direction, MessageType], message: Message) -> None:
        role, _, direction, mtype = key
        rid = message.request_id
        requester = (role is Role.CLIENT and direction is S) or (role is V and direction is R)
        if mtype in REQUESTS and requester:
            self._pending[rid] = mtype
        elif mtype not in REQUESTS and mtype is not T.CLOSE and not (role is V and direction is R):
            # A response settles its request; a client's (fatal) ERROR answers nothing.
            self._pending.pop(rid, None)
        if isinstance(message, Welcome) and direction is R:
            if not self.speaks(message.version):
                self.state = State.CLOSED
                raise UnsupportedVersion(
                    f"the server chose version {message.version}, which this client does not speak"
                )
            self.version = message.version
        self.state = TRANSITIONS[key]
        if isinstance(message, Error) and message.fatal:
            self.state = State.CLOSED
        if self.state is State.CLOSED and mtype is T.CLOSE:
            self._closed_cleanly = True


def _dotted(version: Version) -> str:
    return f"{version[0]}.{version[1]}"


def negotiate_version(
    offered: tuple[Version, ...], supported: tuple[Version, ...] = SUPPORTED_VERSIONS
) -> Version | None:
    """The version to speak: the highest major both sides have, at the lower of the two minors.

    None when there is no common major version.
    """
    ours = {major: minor for major, minor in supported}
    best: Version | None = None
    for major, minor in offered:
        if major in ours:
            candidate = (major, min(minor, ours[major]))
            if best is None or candidate > best:
                best = candidate
    return best
