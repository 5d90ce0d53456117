"""The connection state machine (SPEC.md §5, §6.1): handshake, pipelining, errors, close."""

from __future__ import annotations

import struct

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from protocol import (
    NEED_DATA,
    TRANSITIONS,
    BadMetadata,
    Busy,
    Capture,
    CellvisionError,
    Close,
    Connection,
    ConnectionClosed,
    DeadlineExceeded,
    DuplicateRequestId,
    Error,
    ErrorCode,
    Frame,
    Frames,
    FrameTooLarge,
    Hello,
    Inspect,
    Inspections,
    Limits,
    ListInspections,
    LocalProtocolError,
    MalformedFrame,
    Message,
    MessageType,
    NotAuthenticated,
    OperatorAnswer,
    OperatorCall,
    Ping,
    Pong,
    Result,
    Role,
    ShuttingDown,
    State,
    UnexpectedMessage,
    UnknownMessageType,
    UnsupportedVersion,
    Welcome,
    negotiate_version,
)

Event = Message | ConnectionClosed


def events(conn: Connection, data: bytes) -> list[Event]:
    """Feed ``data`` and collect events until NEED_DATA or CLOSED (errors propagate)."""
    conn.receive_data(data)
    out: list[Event] = []
    while True:
        event = conn.next_event()
        if event is NEED_DATA:
            return out
        assert isinstance(event, Message | ConnectionClosed)
        out.append(event)
        if conn.state is State.CLOSED:  # later calls only say ConnectionClosed
            return out


def one(conn: Connection, data: bytes) -> Event:
    (event,) = events(conn, data)
    return event


def opened(**server_kwargs: object) -> tuple[Connection, Connection]:
    client = Connection(Role.CLIENT)
    server = Connection(Role.SERVER, **server_kwargs)  # type: ignore[arg-type]
    assert one(server, client.send(Hello(1, client="test"))) == Hello(1, client="test")
    assert one(client, server.send(Welcome(1, (1, 0), "srv", "0"))) == Welcome(
        1, (1, 0), "srv", "0"
    )
    return client, server


def raw(mtype: int, rid: int, meta: dict[str, object] | None = None, version=(1, 0)) -> bytes:
    return Frame(mtype, rid, meta or {}, version=version).serialize()


# --------------------------------------------------------------------------- handshake


def test_full_handshake() -> None:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    assert client.state is server.state is State.HANDSHAKE
    hello = client.send(Hello(7, ((1, 3), (0, 9)), "robot/1", "secret"))
    assert hello[4:6] == b"\x01\x01"  # the HELLO header carries the client's newest version
    assert client.pending == {7}
    received = one(server, hello)
    assert received == Hello(7, ((1, 3), (0, 9)), "robot/1", "secret")
    assert server.state is State.HELLO_RECEIVED
    assert server.pending == {7}
    # Client 1.3, server 1.1: the smaller minor of the common major.
    assert negotiate_version(received.versions, server.versions) == (1, 1)
    welcome = server.send(Welcome(7, (1, 1), limits={"max_in_flight": 4}))
    assert server.state is State.OPEN
    assert server.version == (1, 1)
    assert server.pending == frozenset()
    assert one(client, welcome) == Welcome(7, (1, 1), limits={"max_in_flight": 4})
    assert client.state is State.OPEN
    assert client.version == (1, 1)
    assert client.pending == frozenset()


@pytest.mark.parametrize(
    "request_",
    [Ping(2), ListInspections(2), Inspect(2, "x"), Capture(2, "cam"), Close()],
    ids=lambda m: type(m).__name__,
)
def test_requests_before_hello_are_not_authenticated(request_: Message) -> None:
    server = Connection(Role.SERVER)
    with pytest.raises(NotAuthenticated) as info:
        events(server, request_.to_frame((1, 0)).serialize())
    assert info.value.fatal
    assert info.value.request_id == request_.request_id
    assert server.state is State.CLOSED
    # The late fatal ERROR may be sent (with the offending id), and nothing more is read.
    data = server.send(Error.from_exception(info.value))
    assert data[4:6] == b"\x01\x01"  # no version agreed: the server's newest
    with pytest.raises(NotAuthenticated):
        server.next_event()


def test_requests_before_welcome_are_not_authenticated() -> None:
    server = Connection(Role.SERVER)
    server.receive_data(
        raw(MessageType.HELLO, 1, {"versions": [[1, 0]]}) + raw(MessageType.PING, 2)
    )
    assert isinstance(server.next_event(), Hello)
    with pytest.raises(NotAuthenticated):
        server.next_event()
    assert server.state is State.CLOSED


def test_unknown_type_before_hello_is_not_authenticated() -> None:
    server = Connection(Role.SERVER)
    with pytest.raises(NotAuthenticated):
        events(server, raw(0x0777, 1))


def test_unsupported_version_refusal() -> None:
    client = Connection(Role.CLIENT, versions=((2, 0),))
    server = Connection(Role.SERVER)
    hello = one(server, client.send(Hello(1, ((2, 0),))))
    assert isinstance(hello, Hello)
    assert negotiate_version(hello.versions, server.versions) is None
    refusal = Error.from_exception(UnsupportedVersion("no common major", request_id=1))
    assert refusal.fatal
    data = server.send(refusal)
    assert server.state is State.CLOSED
    assert one(client, data) == refusal
    assert client.state is State.CLOSED
    assert client.pending == frozenset()
    assert isinstance(client.next_event(), ConnectionClosed)


def test_wrong_token_refusal() -> None:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    one(server, client.send(Hello(1, auth_token="nope")))
    data = server.send(Error.from_exception(NotAuthenticated("wrong token", request_id=1)))
    assert server.state is State.CLOSED
    error = one(client, data)
    assert isinstance(error, Error)
    assert error.fatal
    assert client.state is server.state is State.CLOSED


def test_non_fatal_answer_to_hello_allows_another_hello() -> None:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    one(server, client.send(Hello(1)))
    busy = server.send(Error.from_exception(Busy("try later", request_id=1)))
    assert server.state is State.HANDSHAKE
    assert isinstance(one(client, busy), Error)
    assert client.state is State.HANDSHAKE
    assert client.pending == server.pending == frozenset()
    one(server, client.send(Hello(2)))
    one(client, server.send(Welcome(2)))
    assert client.state is server.state is State.OPEN


def test_welcome_with_a_version_the_client_does_not_speak() -> None:
    client = Connection(Role.CLIENT)
    client.send(Hello(1))
    with pytest.raises(UnsupportedVersion):
        events(client, raw(MessageType.WELCOME, 1, {"version": [3, 0]}))
    assert client.state is State.CLOSED


def test_welcome_for_another_id_is_unexpected() -> None:
    client = Connection(Role.CLIENT)
    client.send(Hello(1))
    with pytest.raises(UnexpectedMessage):
        events(client, raw(MessageType.WELCOME, 2, {"version": [1, 0]}))
    assert client.state is State.HANDSHAKE


@pytest.mark.parametrize(
    ("offered", "supported", "expected"),
    [
        (((1, 0),), ((1, 0),), (1, 0)),
        (((1, 5),), ((1, 2),), (1, 2)),
        (((1, 2),), ((1, 5),), (1, 2)),
        (((1, 9), (2, 1)), ((1, 3), (2, 4)), (2, 1)),
        (((2, 1), (1, 9)), ((1, 3),), (1, 3)),
        (((3, 0),), ((1, 0), (2, 0)), None),
        (((0, 1),), ((1, 0),), None),
    ],
)
def test_negotiate_version(
    offered: tuple[tuple[int, int], ...],
    supported: tuple[tuple[int, int], ...],
    expected: tuple[int, int] | None,
) -> None:
    assert negotiate_version(offered, supported) == expected


# --------------------------------------------------------------------------- requests


def test_pipelined_requests_answered_out_of_order() -> None:
    client, server = opened()
    data = b"".join(
        client.send(m)
        for m in (Inspect(10, "a"), Ping(11, "p"), Capture(12, "cam"), Inspect(13, "b"))
    )
    assert client.pending == {10, 11, 12, 13}
    received = events(server, data)
    assert [m.request_id for m in received] == [10, 11, 12, 13]  # type: ignore[union-attr]
    assert server.pending == {10, 11, 12, 13}
    answers = [
        Frames(12, "cam"),
        Error.from_exception(Busy("full", request_id=13)),
        Pong(11, "p"),
        Result(10, "a", passed=True),
    ]
    out = b"".join(server.send(m) for m in answers)
    assert server.pending == frozenset()
    assert events(client, out) == answers
    assert client.pending == frozenset()
    assert client.state is server.state is State.OPEN


def test_ids_may_be_reused_once_answered() -> None:
    client, server = opened()
    for _ in range(3):
        one(server, client.send(Ping(5)))
        one(client, server.send(Pong(5)))


def test_response_for_an_unknown_id_is_unexpected_on_the_client() -> None:
    client, server = opened()
    client.send(Ping(3))
    with pytest.raises(UnexpectedMessage) as info:
        events(client, raw(MessageType.PONG, 4))
    assert not info.value.fatal
    assert info.value.request_id == 4
    assert client.state is State.OPEN
    assert client.pending == {3}
    assert one(client, raw(MessageType.PONG, 3)) == Pong(3)


def test_wrong_response_type_fails_the_request() -> None:
    client, _ = opened()
    client.send(Ping(3))
    with pytest.raises(UnexpectedMessage, match="cannot answer PING"):
        events(client, raw(MessageType.RESULT, 3, {"inspection": "x", "verdict": "pass"}))
    assert client.pending == frozenset()  # the request is over: the caller fails it


def test_unusable_response_fails_the_request() -> None:
    client, _ = opened()
    client.send(Inspect(3, "x"))
    with pytest.raises(BadMetadata) as info:
        events(client, raw(MessageType.RESULT, 3, {"inspection": "x", "verdict": "maybe"}))
    assert info.value.request_id == 3
    assert client.pending == frozenset()
    assert client.state is State.OPEN


def test_connection_level_error_on_the_client() -> None:
    client, _ = opened()
    client.send(Ping(3))
    error = one(client, raw(MessageType.ERROR, 0, {"code": 16, "message": "hm"}))
    assert isinstance(error, Error)
    assert client.pending == {3}
    assert client.state is State.OPEN


def test_fatal_error_received_closes() -> None:
    client, _ = opened()
    client.send(Ping(3))
    error = one(client, raw(MessageType.ERROR, 0, {"code": 1, "fatal": True}))
    assert isinstance(error, Error)
    assert error.fatal
    assert client.state is State.CLOSED
    assert isinstance(client.next_event(), ConnectionClosed)
    with pytest.raises(LocalProtocolError):
        client.send(Ping(4))


def test_duplicate_request_id_is_fatal() -> None:
    client, server = opened()
    one(server, client.send(Inspect(9, "x")))
    with pytest.raises(LocalProtocolError, match="in flight"):
        client.send(Inspect(9, "y"))
    with pytest.raises(DuplicateRequestId) as info:
        events(server, raw(MessageType.PING, 9))
    assert info.value.fatal
    assert info.value.request_id == 9
    assert server.state is State.CLOSED
    server.send(Error.from_exception(info.value))


def test_request_id_zero_is_refused_with_a_connection_level_error() -> None:
    client, server = opened()
    with pytest.raises(LocalProtocolError, match="reserved"):
        client.send(Ping(0))
    with pytest.raises(UnexpectedMessage, match="reserved") as info:
        events(server, raw(MessageType.PING, 0))
    assert not info.value.fatal
    assert info.value.request_id == 0
    assert server.pending == frozenset()
    error = one(client, server.send(Error.from_exception(info.value)))
    assert isinstance(error, Error)
    assert error.request_id == 0
    assert client.state is server.state is State.OPEN


def test_unknown_message_type_is_not_fatal() -> None:
    client, server = opened()
    with pytest.raises(UnknownMessageType) as info:
        events(server, raw(0x0042, 8, {"whatever": [1, 2]}))
    assert not info.value.fatal
    assert info.value.request_id == 8
    assert server.state is State.OPEN
    assert server.pending == {8}  # the server owes an ERROR for that id
    data = server.send(Error.from_exception(info.value))
    assert server.pending == frozenset()
    # The connection goes on.
    one(server, client.send(Ping(1)))
    assert one(client, server.send(Pong(1))) == Pong(1)
    # This client never sent id 8 (its Connection cannot send unknown types).
    with pytest.raises(UnexpectedMessage):
        events(client, data)


def test_unknown_message_type_on_the_client() -> None:
    client, _ = opened()
    with pytest.raises(UnknownMessageType):
        events(client, raw(0x0042, 0))
    assert client.state is State.OPEN


def test_messages_in_the_wrong_direction() -> None:
    client, server = opened()
    with pytest.raises(UnexpectedMessage) as info:
        events(server, raw(MessageType.RESULT, 4, {"inspection": "x", "verdict": "pass"}))
    assert server.pending == {4}
    server.send(Error.from_exception(info.value))
    with pytest.raises(UnexpectedMessage):
        events(server, raw(MessageType.HELLO, 5, {"versions": [[1, 0]]}))
    with pytest.raises(UnexpectedMessage):
        events(client, raw(MessageType.INSPECT, 6, {"inspection": "x"}))
    assert client.state is server.state is State.OPEN


def test_bad_metadata_in_a_request_is_answered() -> None:
    client, server = opened()
    with pytest.raises(BadMetadata) as info:
        events(server, raw(MessageType.INSPECT, 4, {"inspection": 1}))
    assert server.pending == {4}
    client._pending[4] = MessageType.INSPECT  # as if this client had sent that frame
    error = one(client, server.send(Error.from_exception(info.value)))
    assert isinstance(error, Error)
    assert error.code == ErrorCode.BAD_METADATA
    assert isinstance(error.to_exception(), BadMetadata)
    assert client.pending == server.pending == frozenset()


@pytest.mark.parametrize("side", ["client", "server"])
def test_wrong_major_after_handshake(side: str) -> None:
    client, server = opened()
    conn = client if side == "client" else server
    mtype = MessageType.PONG if side == "client" else MessageType.PING
    client.send(Ping(1))
    with pytest.raises(UnsupportedVersion) as info:
        events(conn, raw(mtype, 1, version=(2, 0)))
    assert info.value.fatal
    assert conn.state is State.CLOSED


def test_a_newer_minor_in_the_header_is_accepted() -> None:
    client, server = opened()
    assert one(server, raw(MessageType.PING, 1, version=(1, 9))) == Ping(1)


def test_fatal_framing_error_can_be_reported_with_its_request_id() -> None:
    _, server = opened(limits=Limits(max_frame_bytes=100))
    header = struct.pack("<4sBBHHHIII", b"CVIS", 1, 0, MessageType.INSPECT, 0, 0, 77, 0, 500)
    with pytest.raises(FrameTooLarge) as info:
        events(server, header)
    assert info.value.request_id == 77
    error = Error.from_exception(info.value)
    assert error.fatal
    server.send(error)  # not a pending id, but a late fatal ERROR is always allowed
    with pytest.raises(FrameTooLarge):
        server.next_event()


# --------------------------------------------------------------------------- closing


def test_graceful_close_by_the_client() -> None:
    client, server = opened()
    received = events(server, client.send(Inspect(1, "x")) + client.send(Ping(2)))
    assert len(received) == 2
    close = client.send(Close(reason="done"))
    assert client.state is State.CLOSING
    with pytest.raises(LocalProtocolError):
        client.send(Ping(3))  # no new requests after CLOSE
    assert one(server, close) == Close(0, "done")
    assert server.state is State.CLOSING
    assert server.pending == {1, 2}
    # The server answers what is in flight, then closes.
    out = server.send(Pong(2)) + server.send(Result(1, "x", passed=False))
    out += server.send(Close())
    assert server.state is State.CLOSED
    assert events(client, out) == [Pong(2), Result(1, "x"), Close()]
    assert client.state is State.CLOSED
    assert client.pending == frozenset()
    assert isinstance(client.next_event(), ConnectionClosed)
    assert events(client, b"") == [ConnectionClosed()]
    with pytest.raises(LocalProtocolError):
        server.send(Pong(2))


def test_server_initiated_close_at_shutdown() -> None:
    client, server = opened()
    events(server, client.send(Inspect(1, "x")) + client.send(Inspect(2, "y")))
    out = b"".join(
        server.send(Error.from_exception(ShuttingDown("stopping", request_id=rid)))
        for rid in sorted(server.pending)
    )
    assert server.state is State.OPEN  # SHUTTING_DOWN is per request, not fatal
    out += server.send(Close(reason="shutdown"))
    assert server.state is State.CLOSED
    received = events(client, out)
    assert [type(m) for m in received] == [Error, Error, Close]
    assert all(isinstance(m.to_exception(), ShuttingDown) for m in received[:2])  # type: ignore[union-attr]
    assert client.state is State.CLOSED
    assert client.pending == frozenset()
    # Whatever the client still sends is not read any more.
    assert events(server, raw(MessageType.PING, 5)) == [ConnectionClosed()]


def test_server_close_crossing_a_request() -> None:
    client, server = opened()
    close = server.send(Close())
    client.send(Ping(4))  # on the wire while the server closes
    assert one(client, close) == Close()
    assert client.state is State.CLOSED
    assert client.pending == {4}  # never answered: the caller fails it (SPEC §5.6)


def test_close_during_handshake() -> None:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    one(server, client.send(Hello(1)))
    assert one(client, server.send(Close(reason="stopping"))) == Close(0, "stopping")
    assert client.state is server.state is State.CLOSED


def test_eof_with_requests_in_flight_is_an_error_on_the_client() -> None:
    client, server = opened()
    client.send(Ping(1))
    with pytest.raises(MalformedFrame, match="unanswered"):
        events(client, b"")
    assert client.state is State.CLOSED


def test_eof_after_client_close_with_requests_in_flight() -> None:
    client, _ = opened()
    client.send(Ping(1))
    client.send(Close())
    with pytest.raises(MalformedFrame, match="unanswered"):
        events(client, b"")


def test_clean_eof() -> None:
    client, server = opened()
    assert events(client, b"") == [ConnectionClosed()]
    assert events(server, b"") == [ConnectionClosed()]
    assert client.state is server.state is State.CLOSED
    with pytest.raises(LocalProtocolError):
        server.send(Error(0, ErrorCode.INTERNAL_ERROR, "late"))


def test_eof_in_the_middle_of_a_frame() -> None:
    _, server = opened()
    assert events(server, raw(MessageType.PING, 1, {"data": "abc"})[:-1]) == []
    with pytest.raises(MalformedFrame, match="closed"):
        events(server, b"")
    assert server.state is State.CLOSED
    with pytest.raises(MalformedFrame):
        server.next_event()


# --------------------------------------------------------------------------- sending rules


def test_local_protocol_errors() -> None:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    with pytest.raises(LocalProtocolError):
        client.send(Ping(1))  # before the handshake
    with pytest.raises(LocalProtocolError):
        server.send(Welcome(1))  # no HELLO received
    with pytest.raises(LocalProtocolError):
        client.send(Welcome(1))  # wrong direction
    with pytest.raises(LocalProtocolError):
        client.send(Hello(0))  # id 0 is reserved
    client, server = opened()
    with pytest.raises(LocalProtocolError):
        server.send(Result(3, "x"))  # nothing to answer
    one(server, client.send(Ping(3)))
    with pytest.raises(LocalProtocolError, match="cannot answer"):
        server.send(Result(3, "x"))
    with pytest.raises(LocalProtocolError):
        server.send(Ping(4))  # servers send no requests
    with pytest.raises(LocalProtocolError):
        client.send(Pong(3))  # clients send no responses
    with pytest.raises(LocalProtocolError, match="request id 0"):
        client.send(Close(5))
    with pytest.raises(LocalProtocolError):
        client.send(Hello(9))  # the handshake is over
    assert client.state is server.state is State.OPEN


def test_welcome_version_must_be_spoken() -> None:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    one(server, client.send(Hello(1, ((1, 0), (2, 0)))))
    with pytest.raises(LocalProtocolError, match="version"):
        server.send(Welcome(1, (2, 0)))


def test_transition_table_is_consistent() -> None:
    for (role, state, _direction, mtype), after in TRANSITIONS.items():
        assert isinstance(role, Role)
        assert isinstance(mtype, MessageType)
        assert state is not State.CLOSED  # nothing leaves CLOSED
        assert after in State
        if role is Role.CLIENT:
            assert state is not State.HELLO_RECEIVED


# --------------------------------------------------------------------------- state machine


class ClientServerPair(RuleBasedStateMachine):
    """A client and a server with bytes in transit both ways; every step is valid traffic."""

    def __init__(self) -> None:
        super().__init__()
        self.client = Connection(Role.CLIENT)
        self.server = Connection(Role.SERVER)
        self.to_server = b""
        self.to_client = b""
        self.sent: dict[int, Message] = {}  # what the client is waiting for
        self.owed: dict[int, Message] = {}  # what the server received and must answer
        self.next_id = 1

    # -- client

    def _client_send(self, message: Message) -> None:
        self.to_server += self.client.send(message)
        if message.request_id:
            self.sent[message.request_id] = message

    @precondition(lambda self: self.client.state is State.HANDSHAKE and not self.client.pending)
    @rule()
    def hello(self) -> None:
        self._client_send(Hello(self.next_id))
        self.next_id += 1

    @precondition(lambda self: self.client.state is State.OPEN)
    @rule(kind=st.sampled_from(["ping", "list", "inspect", "capture"]), reuse=st.booleans())
    def request(self, kind: str, reuse: bool) -> None:
        rid = self.next_id
        if reuse:  # reuse the smallest id that is free again
            rid = min(set(range(1, self.next_id + 1)) - set(self.client.pending))
        self.next_id = max(self.next_id, rid + 1)
        message = {
            "ping": Ping(rid, "x"),
            "list": ListInspections(rid),
            "inspect": Inspect(rid, "cap"),
            "capture": Capture(rid, "tool", count=2),
        }[kind]
        self._client_send(message)

    @precondition(lambda self: self.client.state is State.OPEN)
    @rule()
    def client_close(self) -> None:
        self._client_send(Close(reason="bye"))

    # -- server

    @precondition(lambda self: self.server.state is State.HELLO_RECEIVED)
    @rule(accept=st.booleans())
    def welcome(self, accept: bool) -> None:
        (rid,) = self.server.pending
        if accept:
            self.to_client += self.server.send(Welcome(rid, (1, 0), "srv", "1"))
        else:
            self.to_client += self.server.send(Error.from_exception(Busy("later", request_id=rid)))
        del self.owed[rid]

    @precondition(
        lambda self: self.server.state in (State.OPEN, State.CLOSING) and self.server.pending
    )
    @rule(data=st.data(), fail=st.booleans())
    def answer(self, data: st.DataObject, fail: bool) -> None:
        rid = data.draw(st.sampled_from(sorted(self.server.pending)))
        request = self.owed.pop(rid)
        answer: Message
        if fail:
            answer = Error.from_exception(Busy("full", request_id=rid))
        elif isinstance(request, Ping):
            answer = Pong(rid, request.data)
        elif isinstance(request, ListInspections):
            answer = Inspections(rid, ({"name": "cap"},))
        elif isinstance(request, Inspect):
            answer = Result(rid, "cap", passed=True, timing={"total_ms": 1.5})
        else:
            answer = Frames(rid, "tool", timestamps=(1.0, 2.0))
        self.to_client += self.server.send(answer)

    @precondition(lambda self: self.server.state is State.CLOSING and not self.server.pending)
    @rule()
    def server_finishes_close(self) -> None:
        self.to_client += self.server.send(Close())

    @precondition(lambda self: self.server.state is State.OPEN)
    @rule()
    def server_shutdown(self) -> None:
        for rid in sorted(self.server.pending):
            self.to_client += self.server.send(
                Error.from_exception(ShuttingDown("stopping", request_id=rid))
            )
            del self.owed[rid]
        self.to_client += self.server.send(Close(reason="shutdown"))

    # -- the wires

    @precondition(lambda self: self.to_server)
    @rule(data=st.data())
    def deliver_to_server(self, data: st.DataObject) -> None:
        n = data.draw(st.integers(1, len(self.to_server)))
        chunk, self.to_server = self.to_server[:n], self.to_server[n:]
        for event in events(self.server, chunk):
            if isinstance(event, Message) and event.request_id:
                self.owed[event.request_id] = event

    @precondition(lambda self: self.to_client)
    @rule(data=st.data())
    def deliver_to_client(self, data: st.DataObject) -> None:
        n = data.draw(st.integers(1, len(self.to_client)))
        chunk, self.to_client = self.to_client[:n], self.to_client[n:]
        for event in events(self.client, chunk):
            if isinstance(event, Close | ConnectionClosed):
                continue
            assert isinstance(event, Message)
            request = self.sent.pop(event.request_id)
            if isinstance(request, Ping) and isinstance(event, Pong):
                assert event.data == request.data

    @precondition(
        lambda self: (
            self.client.state is self.server.state is State.CLOSED
            and not (self.to_server or self.to_client)
        )
    )
    @rule()
    def reconnect(self) -> None:
        assert events(self.client, b"") == events(self.server, b"") == [ConnectionClosed()]
        self.__init__()  # type: ignore[misc]

    # -- invariants

    @invariant()
    def pending_sets_match_the_bookkeeping(self) -> None:
        if self.client.state is not State.CLOSED:
            assert self.client.pending == set(self.sent)
        if self.server.state is not State.CLOSED:
            assert self.server.pending == set(self.owed)

    @invariant()
    def quiet_wires_mean_agreement(self) -> None:
        if self.to_server or self.to_client:
            return
        client, server = self.client.state, self.server.state
        if client is State.HANDSHAKE:
            expected = State.HELLO_RECEIVED if self.client.pending else State.HANDSHAKE
            assert server is expected
        else:
            assert server is client
        if State.CLOSED not in (client, server):
            assert self.client.pending == self.server.pending
            assert self.client.version == self.server.version


TestClientServerPair = ClientServerPair.TestCase
TestClientServerPair.settings = settings(max_examples=60, stateful_step_count=30, deadline=None)


def test_exceptions_are_cellvision_errors() -> None:
    # A smoke check that the documented base class covers what next_event raises above.
    for cls in (NotAuthenticated, DuplicateRequestId, UnknownMessageType, MalformedFrame):
        assert issubclass(cls, CellvisionError)


def _bad_json(mtype: int, rid: int) -> bytes:
    return struct.pack("<4sBBHHHIII", b"CVIS", 1, 0, mtype, 0, 0, rid, 3, 3) + b"{x}"


def test_bad_json_in_a_request_is_not_fatal() -> None:
    client, server = opened()
    with pytest.raises(BadMetadata) as info:
        events(server, _bad_json(MessageType.INSPECT, 4))
    assert info.value.request_id == 4
    assert server.state is State.OPEN
    assert server.pending == {4}
    server.send(Error.from_exception(info.value))
    assert one(server, client.send(Ping(5))) == Ping(5)


def test_bad_json_before_hello_is_not_authenticated() -> None:
    with pytest.raises(NotAuthenticated):
        events(Connection(Role.SERVER), _bad_json(MessageType.PING, 4))


def test_bad_json_in_hello_can_be_answered_and_retried() -> None:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    with pytest.raises(BadMetadata):
        events(server, _bad_json(MessageType.HELLO, 1))
    assert server.state is State.HANDSHAKE
    server.send(Error(1, ErrorCode.BAD_METADATA, "bad JSON"))
    one(server, client.send(Hello(2)))
    one(client, server.send(Welcome(2)))
    assert client.state is server.state is State.OPEN


def test_bad_json_in_a_response_fails_the_request() -> None:
    client, _ = opened()
    client.send(Inspect(4, "x"))
    with pytest.raises(BadMetadata):
        events(client, _bad_json(MessageType.RESULT, 4))
    assert client.pending == frozenset()
    assert client.state is State.OPEN


# --------------------------------------------------------------------------- operator call (1.1)


def opened_at(version: tuple[int, int]) -> tuple[Connection, Connection]:
    client, server = Connection(Role.CLIENT), Connection(Role.SERVER)
    one(server, client.send(Hello(1)))
    one(client, server.send(Welcome(1, version)))
    return client, server


def test_an_operator_call_is_a_request_answered_by_operator_answer_or_error() -> None:
    client, server = opened_at((1, 1))
    call = OperatorCall(5, "cap missing", ("retry", "abort"), deadline_ms=60_000.0)
    assert one(server, client.send(call)) == call
    assert server.pending == client.pending == {5}
    # Other requests go on meanwhile: the call waits for a person, not for the connection.
    one(server, client.send(Ping(6)))
    assert one(client, server.send(Pong(6))) == Pong(6)
    answer = OperatorAnswer(5, "retry", "console 10.0.0.9:5000", 1764000000.5)
    assert one(client, server.send(answer)) == answer
    assert server.pending == client.pending == frozenset()
    # A timeout is an ERROR for the call's id.
    one(server, client.send(OperatorCall(7, "again", deadline_ms=1.0)))
    late = Error.from_exception(DeadlineExceeded("nobody answered", request_id=7))
    assert one(client, server.send(late)) == late
    assert client.state is server.state is State.OPEN


def test_operator_answer_answers_nothing_else() -> None:
    client, server = opened_at((1, 1))
    one(server, client.send(Ping(3)))
    with pytest.raises(LocalProtocolError, match="OPERATOR_ANSWER cannot answer PING"):
        server.send(OperatorAnswer(3, "retry"))
    with pytest.raises(UnexpectedMessage, match="cannot answer PING"):
        events(client, raw(MessageType.OPERATOR_ANSWER, 3, {"choice": "retry"}, (1, 1)))


def test_a_1_0_session_never_sees_an_operator_call() -> None:
    """SPEC §8.2: a type of 1.1 on a connection that agreed on 1.0 is an unknown type, as a
    1.0 server would answer it, and this side refuses to send it."""
    client, server = opened_at((1, 0))
    with pytest.raises(LocalProtocolError, match="belongs to version 1.1"):
        client.send(OperatorCall(2, "x"))
    with pytest.raises(UnknownMessageType, match="agreed on 1.0") as info:
        events(server, raw(MessageType.OPERATOR_CALL, 2, {"message": "x"}))
    assert not info.value.fatal
    assert server.pending == {2}  # the server owes that ERROR, and the connection goes on
    server.send(Error.from_exception(info.value))
    one(server, client.send(Ping(3)))
    assert server.state is State.OPEN


def test_an_operator_call_before_the_handshake_is_not_authenticated() -> None:
    server = Connection(Role.SERVER)
    with pytest.raises(NotAuthenticated):
        events(server, raw(MessageType.OPERATOR_CALL, 2, {"message": "x"}, (1, 1)))
