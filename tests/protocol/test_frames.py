"""Framing (SPEC.md §3): golden bytes, limits, incremental parsing."""

from __future__ import annotations

import re
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import (
    BadMetadata,
    Frame,
    FrameDecoder,
    FrameTooLarge,
    Limits,
    MalformedFrame,
    MessageType,
)
from protocol.frames import as_integer, decode_metadata, encode_metadata

# (frame, bytes written out by hand from the header table of SPEC.md §3.1)
GOLDEN = [
    (
        Frame(MessageType.PING, 1),
        b"CVIS" + b"\x01\x00" + b"\x03\x00" + b"\x00\x00" + b"\x00\x00"
        b"\x01\x00\x00\x00" + b"\x00\x00\x00\x00" + b"\x00\x00\x00\x00",
    ),
    (
        Frame(MessageType.PONG, 0x01020304, {"data": "hi"}),
        b"CVIS\x01\x00\x04\x00\x00\x00\x00\x00"
        b"\x04\x03\x02\x01" + b"\x0d\x00\x00\x00" + b"\x0d\x00\x00\x00" + b'{"data":"hi"}',
    ),
    (
        Frame(MessageType.INSPECT, 2, {"b": 1, "a": "é"}, (b"xy", b"")),
        b"CVIS\x01\x00\x20\x00\x00\x00\x02\x00"
        b"\x02\x00\x00\x00"
        + b"\x10\x00\x00\x00"
        + b"\x1a\x00\x00\x00"
        # keys sorted, compact, UTF-8 (é is two bytes)
        + '{"a":"é","b":1}'.encode()
        + b"\x02\x00\x00\x00\x00\x00\x00\x00"
        + b"xy",
    ),
    (
        Frame(0xBEEF, 0xFFFFFFFF, version=(2, 7), flags=0x8001),
        b"CVIS\x02\x07\xef\xbe\x01\x80\x00\x00\xff\xff\xff\xff" + bytes(8),
    ),
]


@pytest.mark.parametrize(("frame", "data"), GOLDEN)
def test_golden_serialize(frame: Frame, data: bytes) -> None:
    assert frame.serialize() == data


@pytest.mark.parametrize(("frame", "data"), GOLDEN)
def test_golden_parse(frame: Frame, data: bytes) -> None:
    decoder = FrameDecoder()
    decoder.feed(data)
    assert decoder.next_frame() == frame
    assert decoder.next_frame() is None
    assert decoder.buffered == 0


def _header(
    *,
    magic: bytes = b"CVIS",
    mtype: int = MessageType.PING,
    blobs: int = 0,
    rid: int = 1,
    meta: int = 0,
    body: int = 0,
) -> bytes:
    return struct.pack("<4sBBHHHIII", magic, 1, 0, mtype, 0, blobs, rid, meta, body)


def _decode(data: bytes, limits: Limits | None = None, *, eof: bool = False) -> Frame | None:
    decoder = FrameDecoder(limits)
    decoder.feed(data)
    if eof:
        decoder.feed(b"")
    return decoder.next_frame()


def test_too_large_is_fatal_as_soon_as_the_header_arrives() -> None:
    decoder = FrameDecoder(Limits(max_frame_bytes=1000))
    decoder.feed(_header(rid=7, body=977))  # 24 + 977 = 1001 bytes announced, none sent
    with pytest.raises(FrameTooLarge) as info:
        decoder.next_frame()
    assert info.value.fatal
    assert info.value.request_id == 7
    assert info.value.details == {"size": 1001, "max_size": 1000}
    # The decoder stays broken: a fatal error is final.
    decoder.feed(Frame(MessageType.PING, 2).serialize())
    with pytest.raises(FrameTooLarge):
        decoder.next_frame()


def test_frame_exactly_at_the_limit_is_accepted() -> None:
    frame = Frame(MessageType.PING, 1, {"data": "x" * 20})
    data = frame.serialize()
    assert _decode(data, Limits(max_frame_bytes=len(data))) == frame
    with pytest.raises(FrameTooLarge):
        _decode(data, Limits(max_frame_bytes=len(data) - 1))


def test_metadata_limit() -> None:
    data = Frame(MessageType.PING, 1, {"data": "x" * 100}).serialize()
    with pytest.raises(FrameTooLarge) as info:
        _decode(data, Limits(max_metadata_bytes=50))
    assert info.value.fatal


def test_too_many_blobs_is_malformed() -> None:
    with pytest.raises(MalformedFrame):
        _decode(_header(blobs=3, body=12), Limits(max_blobs=2))


def test_bad_magic() -> None:
    with pytest.raises(MalformedFrame, match="magic") as info:
        _decode(_header(magic=b"HTTP"))
    assert info.value.fatal


def test_http_request_is_rejected() -> None:
    with pytest.raises(MalformedFrame):
        _decode(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")


@pytest.mark.parametrize(
    ("blobs", "meta", "body", "rest"),
    [
        (0, 5, 4, b"{}{}"),  # metadata longer than the body
        (2, 0, 7, bytes(7)),  # blob table does not fit
        (1, 0, 6, b"\x03\x00\x00\x00ab"),  # blob says 3 bytes, 2 follow
        (1, 0, 8, b"\x01\x00\x00\x00abcd"),  # blob says 1 byte, 4 follow
        (2, 0, 9, b"\xff\xff\xff\xff\x01\x00\x00\x00a"),  # huge blob length
    ],
)
def test_lengths_that_do_not_add_up(blobs: int, meta: int, body: int, rest: bytes) -> None:
    with pytest.raises(MalformedFrame):
        _decode(_header(mtype=MessageType.INSPECT, blobs=blobs, meta=meta, body=body) + rest)


@pytest.mark.parametrize("cut", [1, 10, 23, 24, 30])
def test_truncated_then_eof(cut: int) -> None:
    data = Frame(MessageType.PONG, 3, {"data": "hello"}).serialize()
    assert _decode(data[:cut]) is None  # just waiting
    with pytest.raises(MalformedFrame, match="closed"):
        _decode(data[:cut], eof=True)


def test_eof_between_frames_is_clean() -> None:
    decoder = FrameDecoder()
    decoder.feed(Frame(MessageType.PING, 1).serialize())
    decoder.feed(b"")
    assert decoder.next_frame() == Frame(MessageType.PING, 1)
    assert decoder.next_frame() is None
    assert decoder.eof


def test_byte_by_byte() -> None:
    frames = [f for f, _ in GOLDEN]
    data = b"".join(f.serialize() for f in frames)
    decoder = FrameDecoder()
    out = []
    for i in range(len(data)):
        decoder.feed(data[i : i + 1])
        frame = decoder.next_frame()
        if frame is not None:
            out.append(frame)
            assert decoder.next_frame() is None
    assert out == frames


def test_many_frames_in_one_chunk() -> None:
    frames = [Frame(MessageType.PING, i, {"data": str(i)}) for i in range(1, 50)]
    decoder = FrameDecoder()
    decoder.feed(b"".join(f.serialize() for f in frames))
    out = []
    while (frame := decoder.next_frame()) is not None:
        out.append(frame)
    assert out == frames


@settings(max_examples=50, deadline=None)
@given(
    st.lists(
        st.builds(
            Frame,
            st.integers(0, 0xFFFF),
            st.integers(0, 0xFFFFFFFF),
            st.dictionaries(
                st.text(max_size=5),
                st.integers(-(2**53 - 1), 2**53 - 1) | st.text(max_size=5),
                max_size=3,
            ),
            st.lists(st.binary(max_size=40), max_size=4).map(tuple),
        ),
        max_size=5,
    ),
    st.data(),
)
def test_any_split_gives_the_same_frames(frames: list[Frame], data: st.DataObject) -> None:
    stream = b"".join(f.serialize() for f in frames)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    decoder = FrameDecoder()
    out = []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        if end > start:  # an empty chunk would mean end of stream
            decoder.feed(stream[start:end])
        while (frame := decoder.next_frame()) is not None:
            out.append(frame)
    assert out == frames


def test_bad_metadata_consumes_its_frame_and_the_stream_goes_on() -> None:
    bad = _header(meta=3, body=3) + b"{x}"
    good = Frame(MessageType.PING, 2).serialize()
    decoder = FrameDecoder()
    decoder.feed(bad + good)
    with pytest.raises(BadMetadata) as info:
        decoder.next_frame()
    assert not info.value.fatal
    assert info.value.request_id == 1
    assert decoder.next_frame() == Frame(MessageType.PING, 2)


@pytest.mark.parametrize(
    "text",
    [
        b"[1]",
        b'"s"',
        b"null",
        b"\xff\xfe",
        b'{"a":NaN}',
        b'{"a":-Infinity}',
        b'{"a":1e400}',
        b'{"a":"\\ud800"}',  # a lone surrogate could never be sent back
        b'{"\\udfff":1}',
        b"\xef\xbb\xbf{}",  # BOM
        b"{" * 5000,
        b"[" * 100000,
        b'{"a":' + b"9" * 5000 + b"}",  # beyond Python's int digit limit
    ],
)
def test_metadata_that_is_not_a_json_object(text: bytes) -> None:
    with pytest.raises(BadMetadata):
        decode_metadata(text, request_id=1)


def test_metadata_edge_cases_that_are_fine() -> None:
    assert decode_metadata(b"", request_id=0) == {}
    assert decode_metadata(b"{}", request_id=0) == {}
    assert decode_metadata(b' { "a" : 1 } ', request_id=0) == {"a": 1}
    assert decode_metadata(b'{"a":"\\ud83d\\ude00"}', request_id=0) == {"a": "\U0001f600"}
    assert decode_metadata(b'{"a":"\\\\ud800"}', request_id=0) == {"a": "\\ud800"}
    assert encode_metadata({}) == b""
    with pytest.raises(ValueError, match="JSON"):
        encode_metadata({"a": float("nan")})


def test_limits_validate() -> None:
    with pytest.raises(ValueError, match="max_blobs"):
        Limits(max_blobs=0)
    with pytest.raises(ValueError, match="2\\*\\*32"):
        Limits(max_frame_bytes=2**32)


# --------------------------------------------------------------------------- JSON profile


def test_null_members_are_absent_at_every_level() -> None:
    meta = b'{"a": null, "b": {"c": null, "d": [null, {"e": null, "f": 1}]}}'
    assert decode_metadata(meta, request_id=3) == {"b": {"d": [None, {"f": 1}]}}


@pytest.mark.parametrize(
    ("text", "why"),
    [
        (b'{"a": 1, "a": 2}', "duplicate member name 'a'"),
        (b'{"x": {"b": 1, "b": null}}', "duplicate member name 'b'"),
        (b'{"n": 9007199254740992}', "outside +/-(2**53 - 1)"),
        (b'{"n": -9007199254740992}', "outside +/-(2**53 - 1)"),
    ],
)
def test_the_i_json_profile_is_enforced(text: bytes, why: str) -> None:
    with pytest.raises(BadMetadata, match=re.escape(why)) as excinfo:
        decode_metadata(text, request_id=9)
    assert excinfo.value.request_id == 9


def test_an_integral_number_is_an_integer_also_when_written_with_a_fraction() -> None:
    assert as_integer(3.0) == 3
    assert as_integer(3) == 3
    assert as_integer(3.5) is None
    assert as_integer(True) is None
    assert as_integer(float(2**60)) is None


@pytest.mark.parametrize(
    ("first", "text"),
    [(b"T", True), (b"T 1\n", True), (b"GET /", True), (b"\x00", False), (b"CVIX", True)],
)
def test_a_wrong_magic_is_refused_at_its_first_differing_byte(first: bytes, text: bool) -> None:
    """A controller's line-protocol ``T 1\\n`` (4 bytes) was held until a full 24-byte header
    arrived (or the handshake timed out): the decoder refuses the prefix at once, and says
    whether it reads as text."""
    decoder = FrameDecoder()
    decoder.feed(first)
    with pytest.raises(MalformedFrame, match="bad magic") as info:
        decoder.next_frame()
    assert info.value.details == {"text": text}


def test_a_partial_magic_waits_for_more() -> None:
    decoder = FrameDecoder()
    decoder.feed(b"CV")
    assert decoder.next_frame() is None
