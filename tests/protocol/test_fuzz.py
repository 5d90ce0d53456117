"""Hostile bytes (SPEC.md §3, §7): only NEED_DATA, messages, ConnectionClosed or documented
CellvisionError subclasses come out, and the server can always answer with an ERROR."""

from __future__ import annotations

import json
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import (
    NEED_DATA,
    CellvisionError,
    Close,
    Connection,
    ConnectionClosed,
    Error,
    Frame,
    Hello,
    ImagePayload,
    Inspect,
    Limits,
    Message,
    MessageType,
    Ping,
    Result,
    Role,
    State,
    Welcome,
)
from protocol.frames import FrameDecoder

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
LIMITS = Limits(max_frame_bytes=4096, max_metadata_bytes=2048, max_blobs=8, max_image_pixels=64)

GRAY = ImagePayload("gray8", 4, 2, bytes(range(8)))
DEPTH = ImagePayload("depth16", 2, 2, bytes(8), "depth")
SERVER_BOUND: list[Message] = [
    Hello(1, ((1, 0), (2, 3)), "fuzz", "token"),
    Ping(2, "data"),
    Inspect(3, "cap", (GRAY, DEPTH), 250.0, True, {"threshold": 0.5, "roi": [1, 2, 3, 4]}),
    Close(reason="bye"),
]
CLIENT_BOUND: list[Message] = [
    Welcome(1, (1, 0), "srv", "0.1", {"max_in_flight": 4}, ({"name": "cap"},), ()),
    Result(
        3, "cap", True, {"features": [{"u": 1.5, "v": 2.0}]}, {"total_ms": 1.0}, "", "", (GRAY,)
    ),
    Error(3, 15, "failed", False, {"why": "dark"}),
]


def server(state: str) -> Connection:
    conn = Connection(Role.SERVER, limits=LIMITS)
    if state == "open":
        conn.receive_data(Hello(9).to_frame((1, 0)).serialize())
        assert isinstance(conn.next_event(), Hello)
        conn.send(Welcome(9))
    return conn


def client(state: str) -> Connection:
    conn = Connection(Role.CLIENT, limits=LIMITS)
    conn.send(Hello(1))
    if state == "open":
        conn.receive_data(Welcome(1).to_frame((1, 0)).serialize())
        assert isinstance(conn.next_event(), Welcome)
        conn.send(Inspect(3, "cap"))
        conn.send(Ping(2))
    return conn


def step(conn: Connection) -> object:
    """One next_event call: its event, or the documented error it raised."""
    try:
        return conn.next_event()
    except CellvisionError as exc:
        return exc


def drain(conn: Connection, chunks: list[bytes]) -> None:
    """Feed the chunks; every outcome must be a documented one."""
    for chunk in chunks:
        conn.receive_data(chunk)
        for _ in range(10_000):  # every call consumes a frame or returns
            event = step(conn)
            if isinstance(event, CellvisionError):
                assert type(event).__module__ == "protocol.errors"
                assert isinstance(event.message, str)
                if conn.role is Role.SERVER:
                    # Whatever went wrong, the server can say so on the wire.
                    assert conn.send(Error.from_exception(event))[:4] == b"CVIS"
                if event.fatal:
                    assert conn.state is State.CLOSED
                    assert type(step(conn)) is type(event)
                    return
                continue
            if event is NEED_DATA:
                break
            if isinstance(event, ConnectionClosed):
                return
            assert isinstance(event, Message)
            if conn.role is Role.SERVER and event.request_id in conn.pending:
                # Answer it so that ids can be reused by later frames.
                conn.send(Error(event.request_id, 16, "fuzz"))
        else:
            raise AssertionError("next_event did not make progress")


def split(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    return [data[a:b] for a, b in zip(points, points[1:], strict=False) if b > a]


roles = st.sampled_from(
    [
        ("server", "handshake"),
        ("server", "open"),
        ("client", "handshake"),
        ("client", "open"),
    ]
)


def connection(role: tuple[str, str]) -> Connection:
    return server(role[1]) if role[0] == "server" else client(role[1])


@FUZZ
@given(roles, st.binary(max_size=400), st.lists(st.integers(0, 400), max_size=4), st.booleans())
def test_arbitrary_bytes(role: tuple[str, str], data: bytes, cuts: list[int], eof: bool) -> None:
    drain(connection(role), [*split(data, cuts), *([b""] if eof else [])])


@FUZZ
@given(roles, st.binary(max_size=200), st.booleans())
def test_arbitrary_bytes_after_a_valid_header(
    role: tuple[str, str], body: bytes, eof: bool
) -> None:
    header = b"CVIS\x01\x00" + struct.pack("<H", MessageType.PING) + bytes(4)
    drain(connection(role), [header + body, *([b""] if eof else [])])


@st.composite
def mutated(draw: st.DrawFn, messages: list[Message]) -> bytes:
    frames = draw(st.lists(st.sampled_from(messages), min_size=1, max_size=3))
    data = bytearray(b"".join(m.to_frame((1, 0)).serialize() for m in frames))
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "cut", "u32", "u16", "insert", "json", "byte"]))
        if kind == "flip":
            position = draw(st.integers(0, len(data) - 1))
            data[position] ^= 1 << draw(st.integers(0, 7))
        elif kind == "cut":
            del data[draw(st.integers(0, len(data))) :]
            if not data:
                data = bytearray(b"C")
        elif kind == "u32":  # a length or id field: header offsets 12, 16, 20, or a blob length
            offset = draw(st.sampled_from([12, 16, 20, 24, 28]))
            value = draw(st.sampled_from([0, 1, 7, 24, 4095, 4096, 2**31, 2**32 - 1]))
            if offset + 4 <= len(data):
                struct.pack_into("<I", data, offset, value)
        elif kind == "u16":  # type, flags, blob count
            offset = draw(st.sampled_from([6, 8, 10]))
            value = draw(st.integers(0, 0xFFFF))
            if offset + 2 <= len(data):
                struct.pack_into("<H", data, offset, value)
        elif kind == "insert":
            position = draw(st.integers(0, len(data)))
            data[position:position] = draw(st.binary(min_size=1, max_size=8))
        elif kind == "byte":
            position = draw(st.integers(0, len(data) - 1))
            data[position] = draw(st.sampled_from([0x00, 0x22, 0x5B, 0x7B, 0x7D, 0xFF, 0xC3]))
        else:  # replace a frame's metadata with other JSON of the same length
            meta = json.dumps(draw(json_values), separators=(",", ":")).encode()
            data = bytearray(_with_metadata(bytes(data), meta))
    return bytes(data)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3)
    ),
    max_leaves=6,
)


def _with_metadata(data: bytes, meta: bytes) -> bytes:
    """The first frame with its metadata replaced by ``meta`` and lengths fixed up."""
    if len(data) < 24:
        return data
    meta_len, body_len = struct.unpack_from("<II", data, 16)
    if meta_len > body_len or 24 + body_len > len(data):
        return data
    header = bytearray(data[:24])
    struct.pack_into("<II", header, 16, len(meta), body_len - meta_len + len(meta))
    return bytes(header) + meta + data[24 + meta_len :]


@FUZZ
@given(st.sampled_from(["handshake", "open"]), mutated(SERVER_BOUND), st.booleans())
def test_mutated_frames_to_the_server(state: str, data: bytes, eof: bool) -> None:
    drain(server(state), [data, *([b""] if eof else [])])


@FUZZ
@given(st.sampled_from(["handshake", "open"]), mutated(CLIENT_BOUND), st.booleans())
def test_mutated_frames_to_the_client(state: str, data: bytes, eof: bool) -> None:
    drain(client(state), [data, *([b""] if eof else [])])


@FUZZ
@given(
    st.sampled_from(list(MessageType)), json_values, st.lists(st.binary(max_size=20), max_size=3)
)
def test_any_metadata_for_any_type(mtype: MessageType, meta: object, blobs: list[bytes]) -> None:
    # Valid framing, arbitrary JSON (not only objects) and blobs for every message type.
    text = json.dumps(meta).encode()
    frame = Frame(mtype, 3, {}, tuple(blobs)).serialize()
    data = _with_metadata(frame, text)
    for state in ("handshake", "open"):
        drain(server(state), [data])
        drain(client(state), [data])


@pytest.mark.parametrize("depth", [10, 500, 990, 5000, 200_000])
@pytest.mark.parametrize("bracket", ["[", '{"a":'])
def test_deeply_nested_json(depth: int, bracket: str) -> None:
    closing = "]" if bracket == "[" else "}"
    nested = bracket * depth + "1" + closing * depth
    for meta in (
        nested,
        '{"inspection":"cap","options":{"x":' + nested + "}}",
        '{"versions":[[1,0]],"client":' + nested + "}",
    ):
        for mtype in (MessageType.HELLO, MessageType.INSPECT, MessageType.RESULT):
            data = _with_metadata(Frame(mtype, 3).serialize(), meta.encode())
            for state in ("handshake", "open"):
                for conn in (
                    Connection(Role.SERVER),
                    Connection(Role.CLIENT),
                    server(state),
                    client(state),
                ):
                    drain(conn, [data])


def test_decoder_alone_never_raises_anything_else() -> None:
    # A quick deterministic sweep over every single-byte change of a frame with blobs.
    data = SERVER_BOUND[2].to_frame((1, 0)).serialize()
    for position in range(len(data)):
        for value in (0x00, 0x7F, 0xFF):
            mutated_data = bytearray(data)
            mutated_data[position] = value
            decoder = FrameDecoder(LIMITS)
            decoder.feed(bytes(mutated_data))
            decoder.feed(b"")
            try:
                while decoder.next_frame() is not None:
                    pass
            except CellvisionError:
                pass
