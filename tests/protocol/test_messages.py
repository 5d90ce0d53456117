"""Messages (SPEC.md §4–§7): round trips of every class, typed errors for bad metadata, images."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import (
    MESSAGE_CLASSES,
    OPERATOR_CHOICES,
    BadImage,
    BadMetadata,
    Capture,
    Close,
    Error,
    Frame,
    FrameDecoder,
    Frames,
    Hello,
    ImageEncoding,
    ImagePayload,
    ImageRole,
    ImageTooLarge,
    Inspect,
    Inspections,
    ListInspections,
    Message,
    MessageType,
    OperatorAnswer,
    OperatorCall,
    Ping,
    Pong,
    Reload,
    Reloaded,
    Result,
    Welcome,
    array_from_payload,
    payload_from_array,
)
from protocol.messages import DecodeContext, message_from_frame

CTX = DecodeContext(max_image_pixels=4096 * 4096)

# --------------------------------------------------------------------------- strategies

ids = st.integers(1, 0xFFFFFFFF)
names = st.text(min_size=1, max_size=12)
texts = st.text(max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False)
positive = st.floats(min_value=1e-3, max_value=1e9)
# I-JSON values (RFC 7493), as senders must write them; a null member is absent on receipt,
# so round trips use none (test_null_members_are_absent_at_every_level covers them).
safe_ints = st.integers(-(2**53 - 1), 2**53 - 1)
json_values = st.recursive(
    st.booleans() | safe_ints | finite | texts,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(texts, inner, max_size=3),
    max_leaves=8,
)
json_objects = st.dictionaries(texts, json_values, max_size=4)
versions = st.tuples(st.integers(0, 255), st.integers(0, 255))
descriptors = st.builds(lambda name, extra: {**extra, "name": name}, names, json_objects)
roles = st.sampled_from(ImageRole)


@st.composite
def images(draw: st.DrawFn) -> ImagePayload:
    encoding = draw(st.sampled_from(ImageEncoding))
    if encoding.is_raw:
        width, height = draw(st.integers(1, 6)), draw(st.integers(1, 6))
        size = width * height * encoding.bytes_per_pixel
        data = draw(st.binary(min_size=size, max_size=size))
    else:
        # The message layer carries compressed bytes as they are; decoding is array_from_payload's.
        width, height = draw(st.integers(0, 9)), draw(st.integers(0, 9))
        data = draw(st.binary(max_size=30))
    return ImagePayload(encoding, width, height, data, draw(roles))


image_lists = st.lists(images(), max_size=3).map(tuple)

MESSAGES: dict[type[Message], st.SearchStrategy[Message]] = {
    Hello: st.builds(
        Hello, ids, st.lists(versions, min_size=1, max_size=3).map(tuple), texts, st.none() | texts
    ),
    Welcome: st.builds(
        Welcome,
        ids,
        versions,
        texts,
        texts,
        st.dictionaries(texts, st.integers(0, 2**40), max_size=4),
        st.lists(descriptors, max_size=2).map(tuple),
        st.lists(descriptors, max_size=2).map(tuple),
    ),
    Ping: st.builds(Ping, ids, texts),
    Pong: st.builds(
        Pong,
        ids,
        texts,
        st.none() | st.builds(lambda extra, ok: {**extra, "ok": ok}, json_objects, st.booleans()),
    ),
    Close: st.builds(Close, st.just(0), texts),
    ListInspections: st.builds(ListInspections, ids),
    Inspections: st.builds(Inspections, ids, st.lists(descriptors, max_size=3).map(tuple)),
    Inspect: st.builds(
        Inspect, ids, names, image_lists, st.none() | positive, st.booleans(), json_objects
    ),
    Result: st.builds(
        Result,
        ids,
        texts,
        st.booleans(),
        json_objects,
        st.dictionaries(texts, finite, max_size=3),
        texts,
        texts,
        image_lists,
        st.none() | st.booleans(),
        st.none() | st.integers(1, 2**53 - 1),
    ),
    Capture: st.builds(
        Capture,
        ids,
        names,
        st.integers(1, 100),
        st.booleans(),
        st.none() | st.sampled_from(["png", "jpeg", "bgr8"]),
        st.none() | positive,
    ),
    Frames: st.builds(
        Frames,
        ids,
        texts,
        image_lists,
        st.lists(finite, max_size=3).map(tuple),
        st.none() | json_objects,
    ),
    Reload: st.builds(Reload, ids),
    Reloaded: st.builds(
        Reloaded,
        ids,
        texts,
        st.lists(descriptors, max_size=2).map(tuple),
        st.lists(descriptors, max_size=2).map(tuple),
    ),
    OperatorCall: st.builds(
        OperatorCall,
        ids,
        names,
        st.permutations(OPERATOR_CHOICES).flatmap(
            lambda all_: st.integers(1, len(all_)).map(lambda n: tuple(all_[:n]))
        ),
        texts,
        texts,
        st.lists(images().filter(lambda i: i.role is not ImageRole.DEPTH), max_size=2).map(tuple),
        st.none() | positive,
        st.none() | st.integers(1, 2**53 - 1),
    ),
    OperatorAnswer: st.builds(
        OperatorAnswer,
        ids,
        st.sampled_from(OPERATOR_CHOICES),
        texts,
        st.none() | finite,
        texts,
        texts,
    ),
    Error: st.builds(
        Error,
        st.integers(0, 0xFFFFFFFF),
        st.integers(0, 0xFFFF),
        texts,
        st.booleans(),
        json_objects,
    ),
}
any_message = st.one_of(*MESSAGES.values())


def decode(data: bytes, ctx: DecodeContext = CTX) -> Message:
    decoder = FrameDecoder()
    decoder.feed(data)
    frame = decoder.next_frame()
    assert frame is not None
    assert decoder.buffered == 0
    return message_from_frame(frame, ctx)


def frame_of(mtype: MessageType, meta: dict[str, Any], blobs: tuple[bytes, ...] = ()) -> Frame:
    return Frame(mtype, 3, meta, blobs)


# --------------------------------------------------------------------------- round trips


def test_every_message_class_has_a_strategy() -> None:
    assert set(MESSAGES) == set(MESSAGE_CLASSES.values())
    assert {cls.TYPE for cls in MESSAGES} == set(MessageType)


@pytest.mark.parametrize("cls", list(MESSAGES), ids=lambda c: c.__name__)
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_round_trip(cls: type[Message], data: st.DataObject) -> None:
    message = data.draw(MESSAGES[cls])
    wire = message.to_frame((1, 0)).serialize()
    assert decode(wire) == message
    # Serializing is deterministic: the decoded message gives the same bytes.
    assert decode(wire).to_frame((1, 0)).serialize() == wire


@settings(max_examples=60, deadline=None)
@given(any_message, json_objects)
def test_unknown_fields_are_ignored(message: Message, extra: dict[str, Any]) -> None:
    frame = message.to_frame((1, 0))
    # Unknown to every message: a drawn key could otherwise be an optional field the message
    # left out (an empty config_hash), whose wrong type is rightly refused.
    unknown = {f"x-unknown-{key}": value for key, value in extra.items()}
    extended = Frame(frame.type, frame.request_id, {**unknown, **frame.metadata}, frame.blobs)
    assert decode(extended.serialize()) == message


def test_spare_blobs_and_shared_blobs_are_accepted() -> None:
    meta = {
        "inspection": "x",
        "images": [
            {"blob": 1, "encoding": "gray8", "width": 1, "height": 1},
            {"blob": 1, "encoding": "gray8", "width": 1, "height": 1, "role": "depth"},
        ],
    }
    message = decode(frame_of(MessageType.INSPECT, meta, (b"unused", b"\x07")).serialize())
    assert isinstance(message, Inspect)
    assert [i.data for i in message.images] == [b"\x07", b"\x07"]
    assert message.images[0].role is ImageRole.COLOR  # role defaults to colour


def test_integer_deadline_is_accepted() -> None:
    message = decode(
        frame_of(MessageType.INSPECT, {"inspection": "x", "deadline_ms": 50}).serialize()
    )
    assert isinstance(message, Inspect)
    assert message.deadline_ms == 50.0


# --------------------------------------------------------------------------- bad metadata

BAD_METADATA = [
    (MessageType.HELLO, {}),
    (MessageType.HELLO, {"versions": []}),
    (MessageType.HELLO, {"versions": [[1]]}),
    (MessageType.HELLO, {"versions": [[1, 256]]}),
    (MessageType.HELLO, {"versions": [[1, True]]}),
    (MessageType.HELLO, {"versions": "1.0"}),
    (MessageType.HELLO, {"versions": [[1, 0]], "client": 5}),
    (MessageType.HELLO, {"versions": [[1, 0]], "auth_token": ["x"]}),
    (MessageType.WELCOME, {}),
    (MessageType.WELCOME, {"version": [1, 0], "limits": {"max_in_flight": "32"}}),
    (MessageType.WELCOME, {"version": [1, 0], "limits": {"max_in_flight": True}}),
    (MessageType.WELCOME, {"version": [1, 0], "inspections": [{"type": "qr"}]}),
    (MessageType.WELCOME, {"version": [1, 0], "cameras": ["tool"]}),
    (MessageType.WELCOME, {"version": [1, 0], "server": "cellvision"}),
    (MessageType.PING, {"data": 1}),
    (MessageType.PONG, {"data": {}}),
    (MessageType.PONG, {"health": "ok"}),
    (MessageType.PONG, {"health": {}}),
    (MessageType.PONG, {"health": {"ok": "yes"}}),
    (MessageType.PONG, {"health": {"ok": 1}}),
    (MessageType.CLOSE, {"reason": False}),
    (MessageType.INSPECTIONS, {"inspections": {}}),
    (MessageType.INSPECT, {}),
    (MessageType.INSPECT, {"inspection": ""}),
    (MessageType.INSPECT, {"inspection": 3}),
    (MessageType.INSPECT, {"inspection": "x", "deadline_ms": 0}),
    (MessageType.INSPECT, {"inspection": "x", "deadline_ms": -5}),
    (MessageType.INSPECT, {"inspection": "x", "deadline_ms": "5"}),
    (MessageType.INSPECT, {"inspection": "x", "deadline_ms": True}),
    (MessageType.INSPECT, {"inspection": "x", "deadline_ms": 10**400}),
    (MessageType.INSPECT, {"inspection": "x", "overlay": 1}),
    (MessageType.INSPECT, {"inspection": "x", "options": []}),
    (MessageType.INSPECT, {"inspection": "x", "images": {}}),
    (MessageType.RESULT, {"inspection": "x"}),
    (MessageType.RESULT, {"inspection": "x", "verdict": "ok"}),
    (MessageType.RESULT, {"inspection": "x", "verdict": True}),
    (MessageType.RESULT, {"verdict": "pass"}),
    (MessageType.RESULT, {"inspection": "x", "verdict": "pass", "data": []}),
    (MessageType.RESULT, {"inspection": "x", "verdict": "pass", "timing": {"total_ms": "1"}}),
    (MessageType.RESULT, {"inspection": "x", "verdict": "pass", "stored": "yes"}),
    (MessageType.RESULT, {"inspection": "x", "verdict": "pass", "stored": 0}),
    (MessageType.CAPTURE, {}),
    (MessageType.CAPTURE, {"camera": ""}),
    (MessageType.CAPTURE, {"camera": "c", "count": 0}),
    (MessageType.CAPTURE, {"camera": "c", "count": 1.5}),
    (MessageType.CAPTURE, {"camera": "c", "depth": "yes"}),
    (MessageType.CAPTURE, {"camera": "c", "deadline_ms": 0.0}),
    (MessageType.FRAMES, {}),
    (MessageType.FRAMES, {"camera": "c", "timestamps": ["now"]}),
    (MessageType.FRAMES, {"camera": "c", "timestamps": [10**400]}),
    (MessageType.FRAMES, {"camera": "c", "intrinsics": [1]}),
    (MessageType.ERROR, {}),
    (MessageType.ERROR, {"code": "5"}),
    (MessageType.ERROR, {"code": 5, "fatal": "yes"}),
    (MessageType.ERROR, {"code": 5, "details": "x"}),
]


@pytest.mark.parametrize(("mtype", "meta"), BAD_METADATA)
def test_bad_metadata(mtype: MessageType, meta: dict[str, Any]) -> None:
    with pytest.raises(BadMetadata) as info:
        decode(frame_of(mtype, meta).serialize())
    assert info.value.request_id == 3
    assert not info.value.fatal


def test_null_means_absent() -> None:
    message = decode(frame_of(MessageType.PING, {"data": None}).serialize())
    assert message == Ping(3)
    with pytest.raises(BadMetadata, match="missing field 'inspection'"):
        decode(frame_of(MessageType.INSPECT, {"inspection": None}).serialize())


def test_constructors_validate() -> None:
    with pytest.raises(ValueError, match="version"):
        Hello(1, ())
    with pytest.raises(ValueError, match="inspection"):
        Inspect(1, "")
    with pytest.raises(ValueError, match="deadline"):
        Inspect(1, "x", deadline_ms=float("inf"))
    with pytest.raises(ValueError, match="count"):
        Capture(1, "c", count=0)
    with pytest.raises(ValueError, match="u32"):
        Ping(2**32)
    with pytest.raises(ValueError, match="u32"):
        Ping(-1)
    with pytest.raises(ValueError, match="boolean 'ok'"):
        Pong(1, health={"result_log": {}})


def test_stored_and_health_are_optional_on_the_wire() -> None:
    """SPEC §5.5, §6.3: absent without a result log or a report, so older peers see no change."""
    result = Result(4, "x", True)
    assert "stored" not in result.to_frame((1, 0)).metadata
    assert result.stored is None
    assert Result(4, "x", True, stored=False).to_frame((1, 0)).metadata["stored"] is False
    assert "health" not in Pong(5).to_frame((1, 0)).metadata
    assert Pong(5).healthy
    assert not Pong(5, health={"ok": False, "result_log": {"failed": 3}}).healthy
    assert Pong(5, health={"ok": True}).healthy


# --------------------------------------------------------------------------- images


def _image_frame(desc: dict[str, Any], blob: bytes) -> bytes:
    return frame_of(MessageType.INSPECT, {"inspection": "x", "images": [desc]}, (blob,)).serialize()


@pytest.mark.parametrize(
    ("encoding", "width", "height", "size"),
    [("gray8", 4, 2, 8), ("bgr8", 4, 2, 24), ("depth16", 4, 2, 16)],
)
def test_raw_lengths(encoding: str, width: int, height: int, size: int) -> None:
    desc = {"blob": 0, "encoding": encoding, "width": width, "height": height}
    assert isinstance(decode(_image_frame(desc, bytes(size))), Inspect)
    for wrong in (size - 1, size + 1, 0):
        with pytest.raises(BadImage, match="needs"):
            decode(_image_frame(desc, bytes(wrong)))
    with pytest.raises(ValueError, match="needs"):
        ImagePayload(ImageEncoding(encoding), width, height, bytes(size + 1))


@pytest.mark.parametrize(
    "desc",
    [
        [],
        {"encoding": "gray8", "width": 1, "height": 1, "blob": 1},
        {"encoding": "gray8", "width": 1, "height": 1, "blob": -1},
        {"encoding": "gray8", "width": 1, "height": 1, "blob": "0"},
        {"encoding": "rgb8", "width": 1, "height": 1, "blob": 0},
        {"encoding": "gray8", "width": 1, "height": 1, "blob": 0, "role": "mask"},
        {"encoding": "gray8", "width": 1, "height": 1, "blob": 0, "role": ["color"]},
        {"encoding": "gray8", "width": -1, "height": 1, "blob": 0},
        {"encoding": "gray8", "width": 1.5, "height": 1, "blob": 0},
        {"encoding": "gray8", "width": True, "height": 1, "blob": 0},
        {"encoding": "gray8", "blob": 0},  # raw images need their size
    ],
)
def test_bad_image_descriptors(desc: Any) -> None:
    with pytest.raises(BadImage) as info:
        decode(_image_frame(desc, b"\x00"))
    assert info.value.request_id == 3


def test_image_too_large() -> None:
    desc = {"blob": 0, "encoding": "gray8", "width": 20, "height": 10}
    with pytest.raises(ImageTooLarge) as info:
        decode(_image_frame(desc, bytes(200)), DecodeContext(max_image_pixels=199))
    assert not info.value.fatal
    assert info.value.details == {"pixels": 200, "width": 20, "height": 10, "max_pixels": 199}
    assert isinstance(decode(_image_frame(desc, bytes(200)), DecodeContext(200)), Inspect)
    # The pixel count is checked before the blob length: no huge allocation is ever trusted.
    huge = {"blob": 0, "encoding": "bgr8", "width": 10**6, "height": 10**6}
    with pytest.raises(ImageTooLarge):
        decode(_image_frame(huge, b""))


def test_image_too_large_details_stay_i_json() -> None:
    """SPEC §4.3: two u32 sides multiply beyond 2**53 - 1, which I-JSON cannot carry; the
    pixel count is clamped and the sides are sent as they are, so the ERROR stays valid."""
    side = 2**32 - 1
    huge = {"blob": 0, "encoding": "gray8", "width": side, "height": side}
    with pytest.raises(ImageTooLarge) as info:
        decode(_image_frame(huge, b""))
    details = info.value.details
    assert details == {"pixels": 2**53 - 1, "width": side, "height": side, "max_pixels": 1 << 24}
    # The ERROR that carries it is a frame our own client accepts (I-JSON, SPEC §3.2).
    error = Error.from_exception(info.value, request_id=3).to_frame((1, 1)).serialize()
    assert decode(error).details == details


def test_depth16_is_little_endian_millimetres() -> None:
    depth = np.array([[0, 1, 258], [1000, 65535, 7]], dtype=np.uint16)
    payload = payload_from_array(depth, role=ImageRole.DEPTH)
    assert payload.encoding is ImageEncoding.DEPTH16
    assert (payload.width, payload.height) == (3, 2)
    assert payload.data == b"\x00\x00\x01\x00\x02\x01\xe8\x03\xff\xff\x07\x00"
    big_endian = depth.astype(">u2")
    assert payload_from_array(big_endian).data == payload.data
    np.testing.assert_array_equal(array_from_payload(payload), depth)


def test_raw_arrays_round_trip_row_major() -> None:
    gray = np.arange(8, dtype=np.uint8).reshape(2, 4)
    payload = payload_from_array(gray)
    assert (payload.encoding, payload.width, payload.height) == (ImageEncoding.GRAY8, 4, 2)
    assert payload.data == bytes(range(8))
    np.testing.assert_array_equal(array_from_payload(payload), gray)
    bgr = np.arange(24, dtype=np.uint8).reshape(2, 4, 3)
    payload = payload_from_array(bgr)
    assert payload.encoding is ImageEncoding.BGR8
    assert payload.data[:3] == bytes([0, 1, 2])  # pixel (0, 0): B, G, R
    np.testing.assert_array_equal(array_from_payload(payload), bgr)
    np.testing.assert_array_equal(array_from_payload(payload_from_array(gray[:, :, None])), gray)


@pytest.mark.parametrize(
    ("array", "encoding"),
    [
        (np.arange(35, dtype=np.uint8).reshape(5, 7), ImageEncoding.PNG),
        (np.arange(105, dtype=np.uint8).reshape(5, 7, 3), ImageEncoding.PNG),
        (np.arange(35, dtype=np.uint16).reshape(5, 7) * 1000, ImageEncoding.PNG),
        (np.full((16, 24), 128, np.uint8), ImageEncoding.JPEG),
        (np.full((16, 24, 3), 77, np.uint8), ImageEncoding.JPEG),
    ],
)
def test_compressed_round_trip(array: np.ndarray, encoding: ImageEncoding) -> None:
    payload = payload_from_array(array, encoding=encoding)
    assert (payload.encoding, payload.width, payload.height) == (
        encoding,
        7 if array.shape[1] == 7 else 24,
        array.shape[0],
    )
    decoded = array_from_payload(payload)
    assert decoded.shape == array.shape
    assert decoded.dtype == array.dtype
    if encoding is ImageEncoding.PNG:
        np.testing.assert_array_equal(decoded, array)  # lossless
    else:
        assert np.abs(decoded.astype(int) - array.astype(int)).max() <= 2
    # Unknown size (0x0) is allowed for compressed images.
    unknown = ImagePayload(encoding, 0, 0, payload.data)
    assert array_from_payload(unknown).shape == array.shape
    # Through a message and back.
    message = Inspect(5, "x", (payload,))
    assert decode(message.to_frame((1, 0)).serialize()) == message


def test_compressed_size_mismatch_and_limits() -> None:
    payload = payload_from_array(np.zeros((10, 20), np.uint8), encoding=ImageEncoding.PNG)
    with pytest.raises(BadImage, match="descriptor says"):
        array_from_payload(ImagePayload("png", 21, 10, payload.data))
    with pytest.raises(ImageTooLarge) as info:
        array_from_payload(payload, max_pixels=199, request_id=4)
    assert info.value.request_id == 4
    assert array_from_payload(payload, max_pixels=200).shape == (10, 20)
    jpeg = payload_from_array(np.zeros((10, 20), np.uint8), encoding=ImageEncoding.JPEG)
    with pytest.raises(ImageTooLarge):
        array_from_payload(jpeg, max_pixels=199)


def test_decompression_bomb_is_refused_before_decoding() -> None:
    # A PNG header announcing 100000 x 100000 pixels, and one empty IDAT behind it.
    ihdr = b"IHDR" + (100000).to_bytes(4, "big") * 2 + bytes([8, 0, 0, 0, 0])
    bomb = b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0d" + ihdr + bytes(4) + bytes(4) + b"IDAT" + bytes(4)
    with pytest.raises(ImageTooLarge):
        array_from_payload(ImagePayload("png", 0, 0, bomb), max_pixels=4096**2)
    # Cut inside IHDR, the size is not established: refused all the same, as BAD_IMAGE.
    with pytest.raises(BadImage, match="truncated"):
        array_from_payload(ImagePayload("png", 0, 0, bomb[:29]), max_pixels=4096**2)


@pytest.mark.parametrize(
    ("encoding", "data"),
    [
        ("png", b""),
        ("png", b"not a png"),
        ("png", b"\x89PNG\r\n\x1a\n" + bytes(40)),
        ("png", b"\xff\xd8\xff\xe0"),  # a JPEG signature under a png label
        ("jpeg", b"\xff\xd8\xff" + bytes(50)),
        ("jpeg", b"\xff\xd8\xff\xc0\x00\x11\x08\x00\x10\x00\x10\x03" + bytes(20)),
        ("jpeg", b"\x89PNG\r\n\x1a\n"),
        ("jpeg", b"GIF89a" + bytes(40)),
    ],
)
def test_undecodable_compressed_images(encoding: str, data: bytes) -> None:
    with pytest.raises(BadImage) as info:
        array_from_payload(ImagePayload(encoding, 0, 0, data), request_id=6)
    assert info.value.request_id == 6


def test_payload_from_array_refuses_what_it_cannot_send() -> None:
    with pytest.raises(ValueError, match="uint8"):
        payload_from_array(np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="cannot be sent"):
        payload_from_array(np.zeros((2, 2), np.uint8), encoding=ImageEncoding.BGR8)
    with pytest.raises(ValueError, match="JPEG"):
        payload_from_array(np.zeros((2, 2), np.uint16), encoding=ImageEncoding.JPEG)


def test_integral_numbers_are_integers_and_nulls_are_absent() -> None:
    """SPEC §3.2: ``5.0`` is the integer 5 (.NET and URScript write it so), and a null member
    is absent (here: the defaults apply) at every level."""
    error = Frame(MessageType.ERROR, 3, {"code": 5.0, "message": None, "details": None})
    decoded = decode(error.serialize())
    assert isinstance(decoded, Error)
    assert decoded.code == 5
    blob = bytes(4)
    inspect = Frame(
        MessageType.INSPECT,
        4,
        {
            "inspection": "i",
            "images": [{"blob": 0.0, "encoding": "gray8", "width": 2.0, "height": 2, "role": None}],
            "deadline_ms": None,
        },
        (blob,),
    )
    message = decode(inspect.serialize())
    assert isinstance(message, Inspect)
    assert message.deadline_ms is None
    (image,) = message.images
    assert (image.width, image.height, image.role) == (2, 2, ImageRole.COLOR)
