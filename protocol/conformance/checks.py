"""The conformance checks. Each is tagged with the SPEC.md section it verifies.

A check passes by returning (optionally a note for the report), fails by raising
:class:`CheckFailed` (or any other exception, reported as an error), and is skipped by raising
:class:`Skip` (the server offers nothing the check can use, e.g. no inspection that takes images
in the request). What a check sends is built from what the server announced in WELCOME: its
inspections, their cameras and the image size a camera declares.
"""

from __future__ import annotations

import json
import os
import struct
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..constants import HEADER, MAGIC, ImageEncoding, ImageRole, MessageType
from ..errors import CellvisionError, ErrorCode
from ..frames import Blob, Frame
from ..images import ImagePayload, payload_from_array, payload_from_descriptor
from ..messages import (
    OPERATOR_CHOICES,
    Capture,
    Close,
    Hello,
    Inspect,
    ListInspections,
    OperatorCall,
    Ping,
    Reload,
)
from .peer import CLOSED, CheckFailed, Peer, Target
from .profiles import Feature

E = ErrorCode
T = MessageType


class Skip(Exception):  # noqa: N818 - it is an outcome, not an error
    """The server offers nothing this check can exercise."""


@dataclass(frozen=True)
class Context:
    """What the checks learn from one handshake: the server's limits, inspections and cameras."""

    target: Target
    limits: dict[str, int]
    inspections: tuple[dict[str, Any], ...]
    cameras: tuple[dict[str, Any], ...]

    def request_inspection(self, *, depth: bool | None = None) -> dict[str, Any]:
        """An inspection whose images arrive in the request (optionally: that takes depth)."""
        for item in self.inspections:
            if item.get("camera_source") == "request" and (
                depth is None or bool(item.get("depth")) == depth
            ):
                return item
        want = "" if depth is None else (" with depth" if depth else " without depth")
        raise Skip(f"the server offers no inspection on a request camera{want}")

    def server_inspection(self) -> dict[str, Any]:
        """An inspection whose camera is on the server (it captures when INSPECT has no
        images)."""
        for item in self.inspections:
            source = item.get("camera_source")
            if isinstance(source, str) and source != "request":
                return item
        raise Skip("the server offers no inspection on a server-side camera")

    def server_camera(self) -> dict[str, Any]:
        """The first camera the server lists whose images it takes itself (not ``"request"``)."""
        for item in self.cameras:
            source = item.get("source")
            if isinstance(source, str) and source != "request" and item.get("name"):
                return item
        raise Skip("the server lists no server-side camera")

    def camera(self, name: object) -> dict[str, Any] | None:
        """The WELCOME's descriptor of the camera ``name``, if it lists one."""
        for item in self.cameras:
            if item.get("name") == name:
                return item
        return None

    def image_size(
        self, item: dict[str, Any], default: tuple[int, int] = (320, 240)
    ) -> tuple[int, int]:
        """``(width, height)`` in pixels of the images the inspection's camera takes, as its
        descriptor declares them (``width``/``height``, else those of its ``intrinsics``),
        else ``default``. An inspection may refuse images of another size than its camera's
        (a depth image must be registered to its colour image), so requests use this size."""
        camera = self.camera(item.get("camera")) or {}
        intrinsics = camera.get("intrinsics")
        for source in (camera, intrinsics if isinstance(intrinsics, dict) else {}):
            width, height = _positive_int(source.get("width")), _positive_int(source.get("height"))
            if width and height:
                return width, height
        return default

    def peer(self) -> Peer:
        return Peer(self.target)

    def open(self) -> Peer:
        peer = Peer(self.target)
        peer.handshake()
        return peer


def _positive_int(value: object) -> int:
    """``value`` when it is a positive JSON integer, else 0."""
    return value if isinstance(value, int) and not isinstance(value, bool) and value > 0 else 0


CheckFn = Callable[[Context], "str | None"]
"""Runs one check; returns nothing or a note for the report (e.g. which answer it accepted)."""


@dataclass(frozen=True)
class Check:
    name: str
    section: str
    description: str
    run: CheckFn
    needs: frozenset[Feature] = frozenset()
    """Optional server features the check exercises (see ``profiles``)."""


CHECKS: list[Check] = []


def check(
    name: str, section: str, description: str, *, needs: frozenset[Feature] = frozenset()
) -> Callable[[CheckFn], CheckFn]:
    def register(fn: CheckFn) -> CheckFn:
        CHECKS.append(Check(name, section, description, fn, needs))
        return fn

    return register


def _frame(
    mtype: int,
    request_id: int,
    metadata: dict[str, Any] | None = None,
    blobs: tuple[Blob, ...] = (),
    version: tuple[int, int] = (1, 0),
) -> Frame:
    return Frame(mtype, request_id, metadata or {}, blobs, version)


def _raw_frame(
    mtype: int,
    request_id: int,
    meta: bytes,
    blobs: tuple[bytes, ...] = (),
    *,
    version: tuple[int, int] = (1, 0),
    body_length: int | None = None,
) -> bytes:
    table = b"".join(struct.pack("<I", len(b)) for b in blobs)
    body = meta + table + b"".join(blobs)
    length = len(body) if body_length is None else body_length
    header = HEADER.pack(
        MAGIC, version[0], version[1], mtype, 0, len(blobs), request_id, len(meta), length
    )
    return header + body


def _test_image(width: int = 320, height: int = 240, *, color: bool = False) -> np.ndarray:
    rng = np.random.default_rng(7)
    shape = (height, width, 3) if color else (height, width)
    return rng.integers(0, 256, size=shape, dtype=np.uint8)


def _still_alive(peer: Peer, request_id: int = 900) -> None:
    peer.send(Ping(request_id, "alive?"))
    pong = peer.expect(T.PONG, request_id=request_id)
    if pong.metadata.get("data") != "alive?":
        raise CheckFailed("the connection answered PING but did not echo its data")


def _result_or_errors(peer: Peer, request_id: int, allowed: set[ErrorCode]) -> Frame:
    frame = peer.recv_frame()
    if frame is CLOSED:
        raise CheckFailed("the server closed the connection instead of answering")
    assert isinstance(frame, Frame)
    if frame.request_id != request_id:
        raise CheckFailed(f"answer for id {frame.request_id}, expected {request_id}")
    if frame.type == T.RESULT:
        if frame.metadata.get("verdict") not in ("pass", "fail"):
            raise CheckFailed(f"RESULT.verdict is {frame.metadata.get('verdict')!r}")
        return frame
    if frame.type == T.ERROR and frame.metadata.get("code") in {int(c) for c in allowed}:
        if frame.metadata.get("fatal"):
            raise CheckFailed(f"error {frame.metadata.get('name')} must not be fatal here")
        return frame
    raise CheckFailed(f"expected RESULT, got type 0x{frame.type:04x} {frame.metadata}")


V1_1 = (1, 1)
"""The protocol version whose rules the checks of protocol 1.1 test; they speak it."""


def _hello(
    peer: Peer,
    ctx: Context,
    offer: tuple[int, int] = V1_1,
    *,
    request_id: int = 1,
    max_frame_bytes: int | None = None,
) -> Frame:
    """Shake hands offering the one version ``offer`` (the HELLO's header carries it too)."""
    hello = Hello(
        request_id, (offer,), "cellvision-conformance", ctx.target.auth_token, max_frame_bytes
    )
    peer.send(hello, version=offer)
    return peer.expect(T.WELCOME, request_id=request_id)


def _open_1_1(ctx: Context, *, max_frame_bytes: int | None = None) -> tuple[Peer, Frame]:
    """A connection that agreed on 1.1, and its WELCOME (a server MAY leave out of a 1.0
    connection what 1.1 added, SPEC §8.2, so 1.1's rules are checked on a 1.1 connection)."""
    peer = ctx.peer()
    try:
        welcome = _hello(peer, ctx, max_frame_bytes=max_frame_bytes)
        _agreed(welcome, V1_1)
    except BaseException:
        peer.close()
        raise
    return peer, welcome


def _agreed(welcome: Frame, version: tuple[int, int]) -> None:
    """WELCOME states ``version`` in its metadata and in its header (SPEC §5.3)."""
    stated = welcome.metadata.get("version")
    if stated != list(version):
        raise CheckFailed(f"WELCOME.version is {stated!r}, expected {list(version)}")
    if welcome.version != version:
        raise CheckFailed(
            f"WELCOME's header carries version {welcome.version}, its metadata {stated!r}"
        )


def _last_frame_size(peer: Peer) -> int:
    """Bytes on the wire (header included) of the frame ``peer`` received last."""
    header = peer.decoder.last_header
    assert header is not None, "no frame received yet"
    return header.frame_length


def _flat_png(width: int, height: int) -> ImagePayload:
    """A uniform grey PNG: a few hundred bytes on the wire and quick to inspect, of any size."""
    flat = np.full((height, width), 128, np.uint8)
    return payload_from_array(flat, encoding=ImageEncoding.PNG)


# ----------------------------------------------------------------------------- handshake


@check("handshake", "§5.1", "HELLO is answered by WELCOME with the same request id")
def _handshake(ctx: Context) -> None:
    with ctx.peer() as peer:
        welcome = peer.handshake(request_id=77)
        meta = welcome.metadata
        if meta.get("version") != [1, 0]:
            raise CheckFailed(f"WELCOME.version is {meta.get('version')!r}, expected [1, 0]")
        server = meta.get("server")
        if not isinstance(server, dict) or not isinstance(server.get("name"), str):
            raise CheckFailed("WELCOME.server must be an object with a string name")


@check(
    "welcome_limits",
    "§5.2",
    "WELCOME states max_frame_bytes, max_image_pixels, max_in_flight as positive integers",
)
def _welcome_limits(ctx: Context) -> None:
    for key in ("max_frame_bytes", "max_image_pixels", "max_in_flight"):
        value = ctx.limits.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise CheckFailed(f"WELCOME.limits.{key} is {value!r}")


@check(
    "welcome_timeouts",
    "§5.2",
    "WELCOME of a 1.1 connection states idle_timeout_ms, frame_timeout_ms, "
    "handshake_timeout_ms and max_in_flight as positive integers",
)
def _welcome_timeouts(ctx: Context) -> str:
    peer, welcome = _open_1_1(ctx)
    with peer:
        limits = welcome.metadata.get("limits")
    if not isinstance(limits, dict):
        raise CheckFailed(f"WELCOME.limits is {limits!r}")
    keys = ("idle_timeout_ms", "frame_timeout_ms", "handshake_timeout_ms", "max_in_flight")
    for key in keys:
        if not _positive_int(limits.get(key)):
            raise CheckFailed(f"WELCOME.limits.{key} is {limits.get(key)!r}")
    return ", ".join(f"{key} {limits[key]}" for key in keys)


MAX_IN_FLIGHT_TRIED = 256
"""The most pipelined requests ``max_in_flight_honoured`` sends (a server may announce more)."""


@check(
    "max_in_flight_honoured",
    "§6.1",
    "on an idle server, max_in_flight pipelined INSPECTs are all run (RESULT), none BUSY",
)
def _max_in_flight(ctx: Context) -> str:
    item = ctx.request_inspection(depth=False)
    image = _flat_png(*ctx.image_size(item, (64, 48)))
    peer, welcome = _open_1_1(ctx)
    with peer:
        limits = welcome.metadata.get("limits")
        announced = _positive_int(limits.get("max_in_flight") if isinstance(limits, dict) else 0)
        if not announced:
            raise CheckFailed("WELCOME.limits.max_in_flight is not a positive integer")
        count = min(announced, MAX_IN_FLIGHT_TRIED)
        ids = range(3000, 3000 + count)
        peer.send_raw(
            b"".join(Inspect(rid, item["name"], (image,)).to_frame(V1_1).serialize() for rid in ids)
        )
        waiting = set(ids)
        while waiting:
            frame = peer.recv_frame()
            if frame is CLOSED:
                raise CheckFailed(f"closed with {len(waiting)} of {count} requests unanswered")
            assert isinstance(frame, Frame)
            if frame.request_id not in waiting:
                raise CheckFailed(f"unexpected answer {_summary(frame)}")
            waiting.discard(frame.request_id)
            if frame.type == T.RESULT:
                continue
            if frame.type == T.ERROR and frame.metadata.get("code") == E.BUSY:
                raise CheckFailed(
                    f"request {frame.request_id - 2999} of {count} was answered BUSY although "
                    f"WELCOME announced max_in_flight {announced}: {_message(frame)}"
                )
            raise CheckFailed(f"expected RESULT, got {_summary(frame)}")
    note = f"{count} INSPECTs in flight, all RESULT"
    return note if count == announced else f"{note} (of max_in_flight {announced})"


@check("welcome_inspections", "§5.2", "WELCOME lists inspections with name, type, camera")
def _welcome_inspections(ctx: Context) -> None:
    for i, item in enumerate(ctx.inspections):
        for key in ("name", "type", "camera"):
            if not isinstance(item.get(key), str):
                raise CheckFailed(f"WELCOME.inspections[{i}].{key} is {item.get(key)!r}")


@check("version_minor_negotiation", "§5.3", "a newer minor is answered with the server's minor")
def _minor(ctx: Context) -> None:
    with ctx.peer() as peer:
        peer.send(Hello(5, ((1, 200),), "conformance", ctx.target.auth_token), version=(1, 200))
        welcome = peer.expect(T.WELCOME, request_id=5)
        version = welcome.metadata.get("version")
        if not (isinstance(version, list) and version[0] == 1 and version[1] <= 200):
            raise CheckFailed(f"negotiated version {version!r} for an offer of 1.200")


@check("version_highest_common_major", "§5.3", "of several majors offered, the common one wins")
def _majors(ctx: Context) -> None:
    with ctx.peer() as peer:
        peer.send(Hello(6, ((9, 0), (1, 0)), "conformance", ctx.target.auth_token))
        welcome = peer.expect(T.WELCOME, request_id=6)
        if welcome.metadata.get("version", [None])[0] != 1:
            raise CheckFailed(f"negotiated {welcome.metadata.get('version')!r}, expected 1.x")


@check("unsupported_version", "§5.3", "no common major: ERROR UNSUPPORTED_VERSION, then close")
def _unsupported(ctx: Context) -> None:
    with ctx.peer() as peer:
        peer.send(Hello(3, ((99, 0),), "conformance", ctx.target.auth_token), version=(99, 0))
        peer.expect_error(E.UNSUPPORTED_VERSION, request_id=3, fatal=True)
        peer.expect_closed()


@check("request_before_hello", "§5.4", "a request before HELLO: NOT_AUTHENTICATED, then close")
def _before_hello(ctx: Context) -> None:
    with ctx.peer() as peer:
        peer.send(Ping(4))
        peer.expect_error(E.NOT_AUTHENTICATED, fatal=True)
        peer.expect_closed()


@check("hello_twice", "§5.7", "a second HELLO is UNEXPECTED_MESSAGE; the connection survives")
def _hello_twice(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send(Hello(8, ((1, 0),), "again", ctx.target.auth_token))
        peer.expect_error(E.UNEXPECTED_MESSAGE, request_id=8, fatal=False)
        _still_alive(peer)


@check(
    "hello_limit_below_welcome",
    "§3.4",
    "a 1.1 HELLO with max_frame_bytes 24, less than any WELCOME: a non-fatal INVALID_ARGUMENT "
    "(an ERROR is sent whatever its size), then a new HELLO without it gets WELCOME",
)
def _hello_limit_below_welcome(ctx: Context) -> None:
    with ctx.peer() as peer:
        hello = Hello(34, (V1_1,), "cellvision-conformance", ctx.target.auth_token, 24)
        peer.send(hello, version=V1_1)
        peer.expect_error(E.INVALID_ARGUMENT, request_id=34, fatal=False)
        _agreed(_hello(peer, ctx, request_id=35), V1_1)
        peer.send(Ping(36, "after"), version=V1_1)
        peer.expect(T.PONG, request_id=36)


@check(
    "wrong_major_after_handshake",
    "§5.3",
    "a frame of another major after WELCOME: UNSUPPORTED_VERSION, then close",
)
def _wrong_major(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send(Ping(9), version=(2, 0))
        peer.expect_error(E.UNSUPPORTED_VERSION, fatal=True)
        peer.expect_closed()


@check(
    "version_1_0_client",
    "§5.3",
    "a client offering only 1.0 gets version [1, 0] (WELCOME metadata and header) and a "
    "working connection",
)
def _version_1_0(ctx: Context) -> None:
    with ctx.peer() as peer:
        _agreed(_hello(peer, ctx, (1, 0), request_id=14), (1, 0))
        peer.send(Ping(15, "1.0"), version=(1, 0))
        pong = peer.expect(T.PONG, request_id=15)
        if pong.version[0] != 1:
            raise CheckFailed(f"PONG carries version {pong.version} on a 1.0 connection")
        peer.send(ListInspections(16), version=(1, 0))
        peer.expect(T.INSPECTIONS, request_id=16)


@check(
    "version_smaller_minor",
    "§5.3",
    "an offer of 1.1 gets [1, 1]; an offer of 1.9 gets the smaller of 9 and the server's "
    "minor (from UNSUPPORTED_VERSION's details.supported when it lists them)",
)
def _version_smaller_minor(ctx: Context) -> str:
    with ctx.peer() as peer:
        _agreed(_hello(peer, ctx, V1_1, request_id=17), V1_1)
    with ctx.peer() as peer:
        welcome = _hello(peer, ctx, (1, 9), request_id=18)
    newest = _newest_minor(ctx)
    version = welcome.metadata.get("version")
    if newest is not None:
        expected = [1, min(9, newest)]
        if version != expected:
            raise CheckFailed(
                f"WELCOME.version is {version!r} for an offer of 1.9 to a server of 1.{newest}, "
                f"expected {expected}"
            )
    elif not (
        isinstance(version, list)
        and len(version) == 2
        and version[0] == 1
        and _positive_int(version[1])
        and version[1] <= 9
    ):
        raise CheckFailed(f"WELCOME.version is {version!r} for an offer of 1.9, expected [1, 1..9]")
    _agreed(welcome, (1, version[1]))
    return f"1.9 offered, 1.{version[1]} agreed" + (
        f" (the server speaks 1.{newest})" if newest is not None else ""
    )


def _newest_minor(ctx: Context) -> int | None:
    """The server's newest minor of major 1, as its refusal of major 99 lists it (a SHOULD of
    §5.3), else None."""
    with ctx.peer() as peer:
        peer.send(Hello(20, ((99, 0),), "conformance", ctx.target.auth_token), version=(99, 0))
        refusal = peer.expect_error(E.UNSUPPORTED_VERSION, request_id=20, fatal=True)
    details = refusal.metadata.get("details")
    supported = details.get("supported") if isinstance(details, dict) else None
    minors = [
        v[1]
        for v in (supported if isinstance(supported, list) else [])
        if isinstance(v, list)
        and len(v) == 2
        and v[0] == 1
        and isinstance(v[1], int)
        and not isinstance(v[1], bool)
    ]
    return max(minors) if minors else None


@check(
    "client_fatal_error",
    "§7",
    "a client's fatal ERROR after the handshake (any request id): the server sends nothing "
    "more and closes the connection",
)
def _client_fatal_error(ctx: Context) -> None:
    for rid in (0, 19):
        peer, _ = _open_1_1(ctx)
        with peer:
            peer.send_frame(_frame(T.ERROR, rid, {"code": 1, "fatal": True}, version=V1_1))
            answer = peer.recv_frame()
            if answer is not CLOSED:
                assert isinstance(answer, Frame)
                raise CheckFailed(
                    f"after the client's fatal ERROR (id {rid}) the server sent "
                    f"{_summary(answer)}; it must send nothing and close"
                )


@check(
    "client_nonfatal_error",
    "§5.7",
    "a client's non-fatal ERROR: UNEXPECTED_MESSAGE with its id; the connection survives",
)
def _client_nonfatal_error(ctx: Context) -> None:
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send_frame(_frame(T.ERROR, 21, {"code": 1, "fatal": False}, version=V1_1))
        peer.expect_error(E.UNEXPECTED_MESSAGE, request_id=21, fatal=False)
        _still_alive(peer)


# ----------------------------------------------------------------------------- keepalive, list


@check("ping_pong", "§5.5", "PING is answered by PONG with the same id and data")
def _ping(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send(Ping(10, "hello, cell"))
        pong = peer.expect(T.PONG, request_id=10)
        if pong.metadata.get("data") != "hello, cell":
            raise CheckFailed(f"PONG.data is {pong.metadata.get('data')!r}")


@check("max_request_id", "§6.1", "request id 0xFFFFFFFF is echoed exactly")
def _max_id(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send(Ping(0xFFFFFFFF))
        peer.expect(T.PONG, request_id=0xFFFFFFFF)


@check("list_inspections", "§6.2", "LIST_INSPECTIONS is answered with the WELCOME's names")
def _list(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send(ListInspections(11))
        answer = peer.expect(T.INSPECTIONS, request_id=11)
        names = {i.get("name") for i in answer.metadata.get("inspections", [])}
        if names != {i.get("name") for i in ctx.inspections}:
            raise CheckFailed(f"INSPECTIONS lists {sorted(map(str, names))}")


@check("unknown_fields_ignored", "§8", "unknown metadata fields are ignored")
def _unknown_fields(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_frame(_frame(T.PING, 12, {"data": "x", "future_field": {"a": [1, 2]}}))
        peer.expect(T.PONG, request_id=12)


@check("unknown_flags_ignored", "§3.5", "unknown header flags are ignored")
def _unknown_flags(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_frame(Frame(T.PING, 13, {}, (), (1, 0), flags=0x8000))
        peer.expect(T.PONG, request_id=13)


# ----------------------------------------------------------------------------- requests


@check("inspect_gray8", "§4.2", "INSPECT with a gray8 image gets a RESULT")
def _gray8(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    image = _test_image(*ctx.image_size(item))
    with ctx.open() as peer:
        peer.send(Inspect(20, item["name"], (payload_from_array(image),)))
        _result_or_errors(peer, 20, set())


@check("inspect_bgr8", "§4.2", "INSPECT with a bgr8 image gets a RESULT")
def _bgr8(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    image = _test_image(*ctx.image_size(item), color=True)
    with ctx.open() as peer:
        peer.send(Inspect(21, item["name"], (payload_from_array(image),)))
        _result_or_errors(peer, 21, set())


@check("inspect_png", "§4.2", "INSPECT with a PNG image gets a RESULT")
def _png(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    image = _test_image(*ctx.image_size(item), color=True)
    payload = payload_from_array(image, encoding=ImageEncoding.PNG)
    with ctx.open() as peer:
        peer.send(Inspect(22, item["name"], (payload,)))
        _result_or_errors(peer, 22, set())


@check("inspect_jpeg", "§4.2", "INSPECT with a JPEG image (size not stated) gets a RESULT")
def _jpeg(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    jpeg = payload_from_array(_test_image(*ctx.image_size(item)), encoding=ImageEncoding.JPEG)
    with ctx.open() as peer:
        peer.send(Inspect(23, item["name"], (ImagePayload(ImageEncoding.JPEG, 0, 0, jpeg.data),)))
        _result_or_errors(peer, 23, set())


@check(
    "inspect_depth16",
    "§4.2",
    "a depth16 image is parsed: RESULT where the inspection takes "
    "depth, else a non-fatal BAD_IMAGE naming it",
)
def _depth16(ctx: Context) -> None:
    try:
        item = ctx.request_inspection(depth=True)
    except Skip:
        item = ctx.request_inspection()
    # Colour and depth of the size the camera declares: a depth image must be registered to
    # its colour image, so a server may refuse a pair of another size than its camera's.
    width, height = ctx.image_size(item)
    depth = np.full((height, width), 1000, np.uint16)
    images = (
        payload_from_array(_test_image(width, height)),
        payload_from_array(depth, role=ImageRole.DEPTH),
    )
    with ctx.open() as peer:
        peer.send(Inspect(24, item["name"], images))
        allowed = {E.INSPECTION_FAILED} if item.get("depth") else {E.BAD_IMAGE}
        _result_or_errors(peer, 24, allowed)
        _still_alive(peer)


@check(
    "inspect_without_images",
    "§6.3",
    "INSPECT without images for an inspection on a request camera: BAD_IMAGE, non-fatal",
)
def _without_images(ctx: Context) -> None:
    item = ctx.request_inspection()
    with ctx.open() as peer:
        peer.send(Inspect(29, item["name"]))
        peer.expect_error(E.BAD_IMAGE, request_id=29, fatal=False)
        _still_alive(peer)


@check(
    "inspect_server_camera",
    "§6.3",
    "INSPECT without images for an inspection on a server camera: the server captures, RESULT",
    needs=frozenset({Feature.SERVER_CAMERAS}),
)
def _server_camera_inspect(ctx: Context) -> str | None:
    item = ctx.server_inspection()
    with ctx.open() as peer:
        peer.send(Inspect(45, item["name"]))
        answer = _result_or_errors(peer, 45, {E.INSPECTION_FAILED, E.CAMERA_UNAVAILABLE})
        _still_alive(peer)
    if answer.type == T.ERROR and answer.metadata.get("code") == E.CAMERA_UNAVAILABLE:
        raise Skip(f"camera {item.get('camera')!r} gives no frame now: {_message(answer)}")
    if answer.type == T.RESULT and answer.metadata.get("inspection") != item["name"]:
        raise CheckFailed(f"RESULT.inspection is {answer.metadata.get('inspection')!r}")
    return f"{item['name']}: {_outcome(answer)}"


@check(
    "inspect_server_camera_images",
    "§6.3",
    "INSPECT with images for an inspection on a server camera: the images are inspected "
    "(RESULT, not INVALID_ARGUMENT)",
    needs=frozenset({Feature.SERVER_CAMERAS}),
)
def _server_camera_images(ctx: Context) -> str:
    item = next(
        (
            i
            for i in ctx.inspections
            if isinstance(i.get("camera_source"), str)
            and i["camera_source"] != "request"
            and not i.get("depth")
        ),
        None,
    )
    if item is None:
        raise Skip("the server offers no inspection on a server-side camera that takes no depth")
    image = payload_from_array(_test_image(*ctx.image_size(item)))
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send(Inspect(49, item["name"], (image,)), version=V1_1)
        answer = _result_or_errors(peer, 49, {E.INSPECTION_FAILED})
        _still_alive(peer)
    if answer.type == T.RESULT and answer.metadata.get("inspection") != item["name"]:
        raise CheckFailed(f"RESULT.inspection is {answer.metadata.get('inspection')!r}")
    return f"{item['name']}: {_outcome(answer)}"


UNKNOWN_OPTION = "conformance_no_such_option"
"""An option key no inspection has."""


@check(
    "unknown_option",
    "§6.3",
    "an unknown key in INSPECT options: INVALID_ARGUMENT naming it in details.option (a server "
    "whose inspections take no options refuses every option alike), non-fatal",
)
def _unknown_option(ctx: Context) -> str:
    item = ctx.request_inspection(depth=False)
    image = _flat_png(*ctx.image_size(item))
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send(Inspect(50, item["name"], (image,), options={UNKNOWN_OPTION: 1}), version=V1_1)
        refusal = peer.expect_error(E.INVALID_ARGUMENT, request_id=50, fatal=False)
        details = refusal.metadata.get("details")
        named = details.get("option") if isinstance(details, dict) else None
        if named == UNKNOWN_OPTION:
            _still_alive(peer)
            return _message(refusal)
        if named is not None:
            raise CheckFailed(f"INVALID_ARGUMENT.details.option is {named!r}, not the unknown key")
        # Not named: right only when the inspection takes no options at all, so that the
        # refusal does not depend on the option: another one must be refused in the same words.
        other = {"conformance_other_option": True}
        peer.send(Inspect(51, item["name"], (image,), options=other), version=V1_1)
        second = peer.expect_error(E.INVALID_ARGUMENT, request_id=51, fatal=False)
        _still_alive(peer)
    if _message(second) != _message(refusal):
        raise CheckFailed(
            f"INVALID_ARGUMENT does not name the option {UNKNOWN_OPTION!r} in details.option: "
            f"{_message(refusal)}"
        )
    return f"no options taken: {_message(refusal)}"


@check(
    "option_camera",
    "§6.3",
    'INSPECT options {"camera": …} (a request cannot change the camera): INVALID_ARGUMENT, '
    "non-fatal",
)
def _option_camera(ctx: Context) -> str:
    item = ctx.request_inspection(depth=False)
    image = _flat_png(*ctx.image_size(item))
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send(Inspect(52, item["name"], (image,), options={"camera": "x"}), version=V1_1)
        refusal = peer.expect_error(E.INVALID_ARGUMENT, request_id=52, fatal=False)
        _still_alive(peer)
    return _message(refusal)


CLIENT_MAX_FRAME_BYTES = 65536
"""The HELLO max_frame_bytes of ``capture_within_client_limit``."""


@check(
    "capture_within_client_limit",
    "§6.4",
    "a client whose HELLO accepts frames of at most 64 KiB (§5.1): a larger CAPTURE reply is "
    "INVALID_ARGUMENT with details.max_size, and no frame it receives is larger",
    needs=frozenset({Feature.SERVER_CAMERAS}),
)
def _capture_within_client_limit(ctx: Context) -> str:
    camera = ctx.server_camera()
    limit = CLIENT_MAX_FRAME_BYTES
    # Raw frames take at least a byte a pixel: enough of them cannot fit in the limit.
    width, height = ctx.image_size({"camera": camera["name"]})
    count = min(16, -(-2 * limit // (width * height)))
    peer, _ = _open_1_1(ctx, max_frame_bytes=limit)
    with peer:
        sizes = [_last_frame_size(peer)]
        peer.send(Capture(53, camera["name"], count=count), version=V1_1)
        answer = peer.recv_frame()
        if answer is CLOSED:
            raise CheckFailed("the server closed the connection instead of answering CAPTURE")
        assert isinstance(answer, Frame)
        sizes.append(_last_frame_size(peer))
        _still_alive(peer)
        sizes.append(_last_frame_size(peer))
    if max(sizes) > limit:
        raise CheckFailed(
            f"the server sent a frame of {max(sizes)} bytes to a client that accepts {limit}"
        )
    if answer.type == T.ERROR and answer.metadata.get("code") == E.CAMERA_UNAVAILABLE:
        raise Skip(f"camera {camera['name']!r} gives no frame now: {_message(answer)}")
    if answer.request_id != 53:
        raise CheckFailed(f"answer for id {answer.request_id}, expected 53")
    if answer.type == T.FRAMES:  # it fitted: nothing to refuse
        return f"{count} frame(s) from {camera['name']!r} fit in {sizes[1]} bytes"
    if answer.type != T.ERROR or answer.metadata.get("code") != E.INVALID_ARGUMENT:
        raise CheckFailed(f"expected INVALID_ARGUMENT, got {_summary(answer)}")
    if answer.metadata.get("fatal"):
        raise CheckFailed("the INVALID_ARGUMENT for a reply too large must not be fatal")
    details = answer.metadata.get("details")
    if not isinstance(details, dict) or details.get("max_size") != limit:
        raise CheckFailed(f"INVALID_ARGUMENT.details is {details!r}, expected max_size {limit}")
    return f"{count} frame(s) from {camera['name']!r}: {_message(answer)}"


@check(
    "capture_request_camera",
    "§6.4",
    "CAPTURE from a camera whose source is the request: INVALID_ARGUMENT, non-fatal",
)
def _capture_request_camera(ctx: Context) -> None:
    camera = next((c for c in ctx.cameras if c.get("source") == "request"), None)
    if camera is None or not isinstance(camera.get("name"), str) or not camera["name"]:
        raise Skip("the server lists no camera whose images arrive in the request")
    with ctx.open() as peer:
        peer.send(Capture(46, camera["name"]))
        peer.expect_error(E.INVALID_ARGUMENT, request_id=46, fatal=False)
        _still_alive(peer)


@check(
    "capture_server_camera",
    "§6.4",
    "CAPTURE from a server camera: FRAMES with a valid colour image (and depth16 when asked)",
    needs=frozenset({Feature.SERVER_CAMERAS}),
)
def _capture_server_camera(ctx: Context) -> str:
    camera = ctx.server_camera()
    depth = camera.get("depth") is True
    with ctx.open() as peer:
        peer.send(Capture(47, camera["name"], depth=depth))
        answer = peer.recv_frame()
        if answer is CLOSED:
            raise CheckFailed("the server closed the connection instead of answering CAPTURE")
        assert isinstance(answer, Frame)
        if answer.type == T.ERROR and answer.metadata.get("code") == E.CAMERA_UNAVAILABLE:
            raise Skip(f"camera {camera['name']!r} gives no frame now: {_message(answer)}")
        if answer.type != T.FRAMES or answer.request_id != 47:
            raise CheckFailed(f"expected FRAMES for id 47, got {_summary(answer)}")
        _still_alive(peer)
    meta = answer.metadata
    if meta.get("camera") != camera["name"]:
        raise CheckFailed(f"FRAMES.camera is {meta.get('camera')!r}, expected {camera['name']!r}")
    images = _frames_images(answer)
    want = [ImageRole.COLOR, ImageRole.DEPTH] if depth else [ImageRole.COLOR]
    if [i.role for i in images] != want:
        raise CheckFailed(f"FRAMES images have roles {[i.role.value for i in images]}")
    if depth and images[1].encoding is not ImageEncoding.DEPTH16:
        raise CheckFailed(f"the depth image is {images[1].encoding.value}, expected depth16")
    return ", ".join(f"{i.role.value} {i.encoding.value} {i.width}x{i.height}" for i in images)


@check(
    "reload",
    "§6.5",
    "RELOAD: RELOADED naming the configuration now served, or INVALID_ARGUMENT where reload "
    "is off; the connection survives",
    needs=frozenset({Feature.RELOAD}),
)
def _reload(ctx: Context) -> str:
    with ctx.open() as peer:
        peer.send(Reload(48))
        answer = peer.recv_frame()
        if answer is CLOSED:
            raise CheckFailed("the server closed the connection instead of answering RELOAD")
        assert isinstance(answer, Frame)
        if answer.request_id != 48:
            raise CheckFailed(f"answer for id {answer.request_id}, expected 48")
        if answer.type == T.ERROR:
            if answer.metadata.get("code") not in (E.INVALID_ARGUMENT, E.CONFIG_INVALID):
                raise CheckFailed(f"RELOAD answered by {_summary(answer)}")
            if answer.metadata.get("fatal"):
                raise CheckFailed("the ERROR answering RELOAD must not be fatal")
            _still_alive(peer)
            return f"{answer.metadata.get('name')}: {_message(answer)}"
        if answer.type != T.RELOADED:
            raise CheckFailed(f"expected RELOADED, got {_summary(answer)}")
        meta = answer.metadata
        if not isinstance(meta.get("config_hash"), str) or not meta["config_hash"]:
            raise CheckFailed(f"RELOADED.config_hash is {meta.get('config_hash')!r}")
        for key in ("inspections", "cameras"):
            items = meta.get(key, [])
            if not isinstance(items, list) or not all(
                isinstance(i, dict) and isinstance(i.get("name"), str) for i in items
            ):
                raise CheckFailed(f"RELOADED.{key} must be a list of objects with a name")
        _still_alive(peer)
    return f"RELOADED, config_hash {meta['config_hash']}"


def _frames_images(answer: Frame) -> list[ImagePayload]:
    descriptors = answer.metadata.get("images")
    if not isinstance(descriptors, list) or not descriptors:
        raise CheckFailed(f"FRAMES.images is {descriptors!r}")
    try:
        return [
            payload_from_descriptor(
                d,
                answer.blobs,
                where=f"FRAMES.images[{i}]",
                request_id=answer.request_id,
                # The server's max_image_pixels bounds what it receives, not what it sends.
                max_pixels=1 << 40,
            )
            for i, d in enumerate(descriptors)
        ]
    except CellvisionError as exc:
        raise CheckFailed(f"FRAMES carries an invalid image: {exc}") from exc


def _message(frame: Frame) -> str:
    return str(frame.metadata.get("message", ""))


def _outcome(frame: Frame) -> str:
    if frame.type == T.RESULT:
        return f"verdict {frame.metadata.get('verdict')}"
    return f"{frame.metadata.get('name')}: {_message(frame)}"


def _summary(frame: Frame) -> str:
    if frame.type == T.ERROR:
        return f"ERROR {frame.metadata.get('code')} {frame.metadata.get('name')}: {_message(frame)}"
    return f"type 0x{frame.type:04x} (id {frame.request_id})"


@check(
    "bad_raw_length",
    "§4.2",
    "a raw image whose blob length does not match: BAD_IMAGE, the connection survives",
)
def _bad_raw(ctx: Context) -> None:
    name = ctx.request_inspection()["name"]
    meta = {
        "inspection": name,
        "images": [{"blob": 0, "encoding": "gray8", "width": 100, "height": 100, "role": "color"}],
    }
    with ctx.open() as peer:
        peer.send_frame(_frame(T.INSPECT, 25, meta, (b"\x00" * 9999,)))
        peer.expect_error(E.BAD_IMAGE, request_id=25, fatal=False)
        _still_alive(peer)


@check("corrupt_png", "§4.2", "a PNG blob that does not decode: BAD_IMAGE")
def _corrupt_png(ctx: Context) -> None:
    name = ctx.request_inspection()["name"]
    meta = {
        "inspection": name,
        "images": [{"blob": 0, "encoding": "png", "width": 0, "height": 0, "role": "color"}],
    }
    blob = b"\x89PNG\r\n\x1a\n" + os.urandom(200)
    with ctx.open() as peer:
        peer.send_frame(_frame(T.INSPECT, 26, meta, (blob,)))
        peer.expect_error(E.BAD_IMAGE, request_id=26, fatal=False)
        _still_alive(peer)


@check("image_too_large", "§4.3", "an image of more pixels than max_image_pixels: IMAGE_TOO_LARGE")
def _too_many_pixels(ctx: Context) -> None:
    name = ctx.request_inspection()["name"]
    side = int(ctx.limits.get("max_image_pixels", 1 << 24) ** 0.5) + 2
    meta = {
        "inspection": name,
        "images": [{"blob": 0, "encoding": "png", "width": side, "height": side, "role": "color"}],
    }
    with ctx.open() as peer:
        peer.send_frame(_frame(T.INSPECT, 27, meta, (_tiny_png(),)))
        peer.expect_error(E.IMAGE_TOO_LARGE, request_id=27, fatal=False)
        _still_alive(peer)


@check(
    "png_bomb",
    "§4.3",
    "a small PNG that declares more pixels than max_image_pixels: "
    "IMAGE_TOO_LARGE, not an out-of-memory",
)
def _png_bomb(ctx: Context) -> None:
    name = ctx.request_inspection()["name"]
    side = int(ctx.limits.get("max_image_pixels", 1 << 24) ** 0.5) + 2
    meta = {
        "inspection": name,
        "images": [{"blob": 0, "encoding": "png", "width": 0, "height": 0, "role": "color"}],
    }
    with ctx.open() as peer:
        peer.send_frame(_frame(T.INSPECT, 28, meta, (_tiny_png(side, side),)))
        peer.expect_error(E.IMAGE_TOO_LARGE, request_id=28, fatal=False)
        _still_alive(peer)


@check(
    "image_too_large_u32_sides",
    "§4.3",
    "a raw image of (2^32 - 1) x (2^32 - 1) pixels: IMAGE_TOO_LARGE whose details stay I-JSON "
    "(pixels at most 2^53 - 1), non-fatal",
)
def _u32_sides(ctx: Context) -> None:
    name = ctx.request_inspection()["name"]
    side = 2**32 - 1
    meta = {
        "inspection": name,
        "images": [{"blob": 0, "encoding": "gray8", "width": side, "height": side}],
    }
    with ctx.open() as peer:
        # The peer's decoder refuses integers beyond 2^53 - 1: an ERROR with the exact
        # product fails this check as a frame that is not valid protocol 1.
        peer.send_frame(_frame(T.INSPECT, 32, meta, (b"",)))
        peer.expect_error(E.IMAGE_TOO_LARGE, request_id=32, fatal=False)
        _still_alive(peer)


@check(
    "jpeg_ends_before_its_scan",
    "§4.3",
    "a JPEG whose SOF announces 65000 x 65000 and that ends before its scan: BAD_IMAGE (its size "
    "is never established), non-fatal",
)
def _jpeg_without_scan(ctx: Context) -> None:
    name = ctx.request_inspection()["name"]
    # SOI, then a baseline SOF0 of one 8-bit component, 65000 x 65000, and nothing more.
    sof = b"\xff\xc0\x00\x0b\x08" + (65000).to_bytes(2, "big") * 2 + b"\x01\x01\x11\x00"
    meta = {"inspection": name, "images": [{"blob": 0, "encoding": "jpeg"}]}
    with ctx.open() as peer:
        peer.send_frame(_frame(T.INSPECT, 33, meta, (b"\xff\xd8" + sof,)))
        peer.expect_error(E.BAD_IMAGE, request_id=33, fatal=False)
        _still_alive(peer)


@check("unknown_inspection", "§7", "INSPECT of an unknown name: UNKNOWN_INSPECTION, non-fatal")
def _unknown_inspection(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send(
            Inspect(
                30,
                "no-such-inspection-\u00e6\u00f8\u00e5",
                (payload_from_array(_test_image(8, 8)),),
            )
        )
        peer.expect_error(E.UNKNOWN_INSPECTION, request_id=30, fatal=False)
        _still_alive(peer)


@check("unknown_camera", "§6.4", "CAPTURE from an unknown camera: UNKNOWN_CAMERA, non-fatal")
def _unknown_camera(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_frame(_frame(T.CAPTURE, 31, {"camera": "no-such-camera", "count": 1}))
        peer.expect_error(E.UNKNOWN_CAMERA, request_id=31, fatal=False)
        _still_alive(peer)


@check(
    "bad_metadata_json",
    "§3.2",
    "metadata that is not JSON: BAD_METADATA with the id, the connection survives",
)
def _bad_json(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_raw(_raw_frame(T.INSPECT, 32, b'{"inspection": '))
        peer.expect_error(E.BAD_METADATA, request_id=32, fatal=False)
        _still_alive(peer)


@check("metadata_not_object", "§3.2", "metadata that is a JSON array: BAD_METADATA")
def _not_object(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_raw(_raw_frame(T.PING, 33, b"[1, 2, 3]"))
        peer.expect_error(E.BAD_METADATA, request_id=33, fatal=False)
        _still_alive(peer)


@check(
    "null_is_absent",
    "§3.2",
    "null members are absent at every level: an image's role, a PNG's width and height, "
    "deadline_ms, overlay, options; the INSPECTs get RESULTs",
)
def _null_is_absent(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    width, height = ctx.image_size(item)
    gray = np.full((height, width), 128, np.uint8).tobytes()
    png = _flat_png(width, height)
    raw_meta = {
        "inspection": item["name"],
        "deadline_ms": None,
        "overlay": None,
        "options": None,
        "images": [
            {"blob": 0, "encoding": "gray8", "width": width, "height": height, "role": None}
        ],
    }
    png_meta = {
        "inspection": item["name"],
        "images": [{"blob": 0, "encoding": "png", "width": None, "height": None, "role": "color"}],
    }
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send_frame(_frame(T.INSPECT, 54, raw_meta, (gray,), version=V1_1))
        _result_or_errors(peer, 54, set())
        peer.send_frame(_frame(T.INSPECT, 55, png_meta, (png.data,), version=V1_1))
        _result_or_errors(peer, 55, set())


@check(
    "duplicate_member_names",
    "§3.2",
    "metadata with a member name twice (I-JSON): BAD_METADATA, the connection survives",
)
def _duplicate_names(ctx: Context) -> None:
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send_raw(_raw_frame(T.PING, 56, b'{"data":"a","data":"b"}', version=V1_1))
        peer.expect_error(E.BAD_METADATA, request_id=56, fatal=False)
        _still_alive(peer)


@check(
    "integer_beyond_2_53",
    "§3.2",
    "an integer beyond 2^53-1 (I-JSON), even in an unknown field: BAD_METADATA, the "
    "connection survives",
)
def _integer_beyond_2_53(ctx: Context) -> None:
    meta = b'{"data":"a","conformance_count":9007199254740992}'
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send_raw(_raw_frame(T.PING, 57, meta, version=V1_1))
        peer.expect_error(E.BAD_METADATA, request_id=57, fatal=False)
        _still_alive(peer)


@check(
    "integral_number_as_integer",
    "§3.2",
    "an integer written as 64.0 (an image's blob, width and height) is accepted: RESULT",
)
def _integral_number(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    width, height = ctx.image_size(item)
    meta = {
        "inspection": item["name"],
        "images": [
            {
                "blob": 0.0,
                "encoding": "gray8",
                "width": float(width),
                "height": float(height),
                "role": "color",
            }
        ],
    }
    peer, _ = _open_1_1(ctx)
    with peer:
        blob = np.full((height, width), 128, np.uint8).tobytes()
        peer.send_frame(_frame(T.INSPECT, 58, meta, (blob,), version=V1_1))
        _result_or_errors(peer, 58, set())


@check(
    "numbers_in_unknown_fields",
    "§3.2",
    "an unknown field holding 1e300 is ignored (RESULT); one holding the integer 2^53 + 1 is "
    "BAD_METADATA (I-JSON), non-fatal",
)
def _numbers_in_unknown_fields(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    width, height = ctx.image_size(item)
    blob = np.full((height, width), 128, np.uint8).tobytes()
    image = f'{{"blob":0,"encoding":"gray8","width":{width},"height":{height}}}'
    name = json.dumps(item["name"])
    # Written by hand: this library's own encoder would refuse the second one.
    double = f'{{"inspection":{name},"images":[{image}],"x_later":1e300}}'.encode()
    too_big = f'{{"inspection":{name},"images":[{image}],"x_later":9007199254740993}}'.encode()
    with ctx.open() as peer:
        peer.send_raw(_raw_frame(T.INSPECT, 59, double, (blob,)))
        _result_or_errors(peer, 59, set())
        peer.send_raw(_raw_frame(T.INSPECT, 60, too_big, (blob,)))
        peer.expect_error(E.BAD_METADATA, request_id=60, fatal=False)
        _still_alive(peer)


@check("missing_field", "§6.3", "INSPECT without its inspection name: BAD_METADATA")
def _missing_field(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_frame(_frame(T.INSPECT, 34, {"deadline_ms": 100}))
        peer.expect_error(E.BAD_METADATA, request_id=34, fatal=False)
        _still_alive(peer)


@check("bad_deadline", "§6.1", "a negative deadline_ms: BAD_METADATA")
def _bad_deadline(ctx: Context) -> None:
    name = ctx.request_inspection()["name"]
    with ctx.open() as peer:
        peer.send_frame(_frame(T.INSPECT, 35, {"inspection": name, "deadline_ms": -5}))
        peer.expect_error(E.BAD_METADATA, request_id=35, fatal=False)
        _still_alive(peer)


@check(
    "deadline",
    "§6.1",
    "a deadline too short to meet: DEADLINE_EXCEEDED (or a RESULT if "
    "the server was that fast), never silence",
)
def _deadline(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    image = payload_from_array(_test_image(*ctx.image_size(item, (1024, 768))))
    with ctx.open() as peer:
        peer.send(Inspect(36, item["name"], (image,), deadline_ms=0.001))
        _result_or_errors(peer, 36, {E.DEADLINE_EXCEEDED})
        _still_alive(peer)


@check(
    "unknown_message_type",
    "§8",
    "an unknown message type: UNKNOWN_MESSAGE_TYPE with its id; the connection survives",
)
def _unknown_type(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_frame(_frame(0x7A7A, 37, {"something": "new"}))
        peer.expect_error(E.UNKNOWN_MESSAGE_TYPE, request_id=37, fatal=False)
        _still_alive(peer)


@check(
    "unexpected_direction",
    "§5.7",
    "a server-to-client message sent by the client: UNEXPECTED_MESSAGE, non-fatal",
)
def _wrong_direction(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_frame(_frame(T.PONG, 38))
        peer.expect_error(E.UNEXPECTED_MESSAGE, request_id=38, fatal=False)
        _still_alive(peer)


@check(
    "pipelining",
    "§6.1",
    "many requests sent back to back are all answered, matched by id (order free)",
)
def _pipelining(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    big = payload_from_array(_test_image(*ctx.image_size(item, (1024, 768))))
    with ctx.open() as peer:
        batch = b"".join(
            [Inspect(100, item["name"], (big,)).to_frame((1, 0)).serialize()]
            + [Ping(101 + i, str(i)).to_frame((1, 0)).serialize() for i in range(8)]
            + [ListInspections(110).to_frame((1, 0)).serialize()]
        )
        peer.send_raw(batch)
        expected = {100: T.RESULT, 110: T.INSPECTIONS} | {101 + i: T.PONG for i in range(8)}
        seen: list[int] = []
        while len(seen) < len(expected):
            frame = peer.recv_frame()
            if frame is CLOSED:
                raise CheckFailed(f"closed after {len(seen)} of {len(expected)} answers")
            assert isinstance(frame, Frame)
            want = expected.get(frame.request_id)
            if want is None or frame.request_id in seen:
                raise CheckFailed(f"unexpected answer id {frame.request_id}")
            if frame.type != want and frame.type != T.ERROR:
                raise CheckFailed(f"id {frame.request_id} answered by type 0x{frame.type:04x}")
            if frame.type == T.ERROR and frame.metadata.get("code") != E.BUSY:
                raise CheckFailed(f"id {frame.request_id}: error {frame.metadata}")
            seen.append(frame.request_id)


@check(
    "duplicate_request_id",
    "§6.1",
    "a request id reused while in flight: DUPLICATE_REQUEST_ID, then close",
)
def _duplicate(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    small = payload_from_array(_test_image(16, 16))
    # Both copies go out in one small write, so the server reads the second before it can
    # have answered the first. If it still answered both, that was no duplicate: try again.
    for attempt in range(3):
        with ctx.open() as peer:
            rid = 200 + attempt
            frame = Inspect(rid, item["name"], (small,)).to_frame((1, 0)).serialize()
            peer.send_raw(frame + frame)
            results = 0
            while results < 2:
                got = peer.recv_frame()
                if got is CLOSED:
                    raise CheckFailed("closed without DUPLICATE_REQUEST_ID")
                assert isinstance(got, Frame)
                if got.type == T.ERROR and got.metadata.get("code") == E.DUPLICATE_REQUEST_ID:
                    if got.metadata.get("fatal") is not True:
                        raise CheckFailed("DUPLICATE_REQUEST_ID must be fatal")
                    peer.expect_closed()
                    return
                results += 1
    raise CheckFailed("the server answered both copies of a request id three times over")


# ----------------------------------------------------------------------------- framing abuse


@check(
    "oversize_frame",
    "§3.4",
    "a header announcing more than max_frame_bytes: FRAME_TOO_LARGE at once, then close",
)
def _oversize(ctx: Context) -> None:
    limit = ctx.limits.get("max_frame_bytes", 1 << 26)
    with ctx.open() as peer:
        body_length = min(limit + 1, 0xFFFFFFFF - 24)
        peer.send_raw(HEADER.pack(MAGIC, 1, 0, T.INSPECT, 0, 0, 40, 0, body_length))
        peer.expect_error(E.FRAME_TOO_LARGE, fatal=True)
        peer.expect_closed()


@check(
    "refused_at_header",
    "§3.1",
    "before HELLO, an INSPECT header announcing a body (60 MiB, and 60 KiB: below the "
    "handshake's frame limit) that is never sent: NOT_AUTHENTICATED at once, then close",
)
def _refused_at_header(ctx: Context) -> None:
    for rid, body_length in ((59, 60 << 20), (62, 60 << 10)):
        with ctx.peer() as peer:
            peer.send_raw(HEADER.pack(MAGIC, *V1_1, T.INSPECT, 0, 0, rid, 0, body_length))
            peer.expect_error(E.NOT_AUTHENTICATED, request_id=rid, fatal=True)
            peer.expect_closed()


@check("garbage", "§3.1", "bytes without the magic: MALFORMED_FRAME, then close")
def _garbage(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_raw(b"GET / HTTP/1.1\r\nHost: cell\r\n\r\n")
        peer.expect_error(E.MALFORMED_FRAME, fatal=True)
        peer.expect_closed()


@check(
    "wrong_magic_at_once",
    "§3.1",
    "another protocol's short text line before HELLO: MALFORMED_FRAME at once (not after a "
    "24-byte header or the handshake timeout), then close",
)
def _wrong_magic_at_once(ctx: Context) -> None:
    with ctx.peer() as peer:
        peer.send_raw(b"T 1\n")  # a line-protocol trigger: 4 bytes, the stream stays open
        peer.expect_error(E.MALFORMED_FRAME, fatal=True)
        peer.expect_closed()


@check(
    "inconsistent_lengths", "§3.3", "blob lengths that do not add up: MALFORMED_FRAME, then close"
)
def _inconsistent(ctx: Context) -> None:
    with ctx.open() as peer:
        meta = b'{"data":"x"}'
        frame = bytearray(_raw_frame(T.PING, 41, meta, (b"abcd",)))
        # Blob table says 4 bytes; claim 5 instead: the sum no longer matches the body length.
        offset = 24 + len(meta)
        frame[offset : offset + 4] = struct.pack("<I", 5)
        peer.send_raw(bytes(frame))
        peer.expect_error(E.MALFORMED_FRAME, fatal=True)
        peer.expect_closed()


@check(
    "truncated_then_disconnect",
    "§3.4",
    "half a frame then end of stream: the server closes the connection and keeps serving others",
)
def _truncated(ctx: Context) -> None:
    with ctx.open() as peer:
        data = Ping(42, "x" * 100).to_frame((1, 0)).serialize()
        peer.send_raw(data[: len(data) // 2])
        peer.shutdown_write()
        peer.expect_closed()
    with ctx.open() as other:
        _still_alive(other)


@check(
    "graceful_close", "§5.6", "CLOSE after a request: the answer, then CLOSE, then end of stream"
)
def _graceful(ctx: Context) -> None:
    with ctx.open() as peer:
        peer.send_raw(
            Ping(43).to_frame((1, 0)).serialize() + Close(0, "done").to_frame((1, 0)).serialize()
        )
        peer.expect(T.PONG, request_id=43)
        peer.expect(T.CLOSE)
        peer.expect_closed()


@check(
    "request_after_close",
    "§5.6",
    "a request after the client's CLOSE is neither run nor answered; what was in flight is "
    "answered, then CLOSE, then end of stream",
)
def _request_after_close(ctx: Context) -> None:
    item = ctx.request_inspection(depth=False)
    image = _flat_png(*ctx.image_size(item))
    peer, _ = _open_1_1(ctx)
    with peer:
        peer.send_raw(
            Inspect(60, item["name"], (image,)).to_frame(V1_1).serialize()
            + Close(0, "done").to_frame(V1_1).serialize()
            + Ping(61, "late").to_frame(V1_1).serialize()
        )
        answered = False
        while True:
            frame = peer.recv_frame()
            if frame is CLOSED:
                raise CheckFailed("the server closed the connection without sending CLOSE")
            assert isinstance(frame, Frame)
            if frame.type == T.CLOSE:
                break
            if frame.request_id == 61:
                raise CheckFailed(f"the request sent after CLOSE was answered: {_summary(frame)}")
            if frame.request_id != 60 or answered:
                raise CheckFailed(f"unexpected {_summary(frame)} after the client's CLOSE")
            failed = frame.type == T.ERROR and frame.metadata.get("code") == E.INSPECTION_FAILED
            if frame.type != T.RESULT and not failed:
                raise CheckFailed(f"the INSPECT in flight was answered {_summary(frame)}")
            answered = True
        if not answered:
            raise CheckFailed("the server sent CLOSE without answering the INSPECT in flight")
        after = peer.recv_frame()
        if after is not CLOSED:
            assert isinstance(after, Frame)
            raise CheckFailed(f"the server sent {_summary(after)} after its CLOSE")


@check(
    "other_clients_undisturbed",
    "§2",
    "while one client sends garbage, another connection keeps getting answers",
)
def _isolation(ctx: Context) -> None:
    with ctx.open() as good, ctx.open() as bad:
        bad.send_raw(os.urandom(64))
        for i in range(5):
            _still_alive(good, 500 + i)
            time.sleep(0.01)


def _tiny_png(width: int = 1, height: int = 1) -> bytes:
    """A valid PNG header declaring width x height, with a tiny (truncated) image stream."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    rows = zlib.compress(b"\x00" + b"\x80" * min(width, 64))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", rows) + chunk(b"IEND", b"")


@check(
    "two_colour_images",
    "§4.1",
    "INSPECT with two color-role images (a depth image sent without its role is one): "
    "BAD_IMAGE, non-fatal",
)
def _two_colour_images(ctx: Context) -> str:
    item = ctx.request_inspection(depth=False)
    image = _flat_png(*ctx.image_size(item))
    with ctx.open() as peer:
        peer.send(Inspect(61, item["name"], (image, image)))
        refusal = peer.expect_error(E.BAD_IMAGE, request_id=61, fatal=False)
        _still_alive(peer)
    return _message(refusal)


@check(
    "connection_limit_busy_is_fatal",
    "§5.4",
    "at its announced max_connections the server answers the next HELLO with BUSY, fatal, and "
    "closes",
)
def _connection_limit_busy_is_fatal(ctx: Context) -> str:
    # max_connections is a 1.1 limit: a server need not announce it on a 1.0 connection (§8.2).
    peer_1_1, welcome = _open_1_1(ctx)
    peer_1_1.close()
    limits = welcome.metadata.get("limits")
    limit = limits.get("max_connections") if isinstance(limits, dict) else None
    if not isinstance(limit, int) or limit < 1:
        raise Skip("the server does not announce max_connections")
    if limit > 256:
        raise Skip(f"max_connections is {limit}: too many connections to open for a check")
    held: list[Peer] = []
    try:
        # This check's own connections, plus any the suite or others hold: open until refused.
        for _ in range(limit + 1):
            peer = ctx.peer()
            held.append(peer)
            peer.send(Hello(1, ((1, 0),), "cellvision-conformance", ctx.target.auth_token))
            answer = peer.recv_frame()
            if answer is CLOSED:
                raise CheckFailed("the server closed a connection without answering its HELLO")
            assert isinstance(answer, Frame)
            if answer.type == MessageType.WELCOME:
                continue
            if answer.type != MessageType.ERROR or answer.metadata.get("code") != int(E.BUSY):
                raise CheckFailed(f"expected WELCOME or BUSY, got {_message(answer)}")
            if answer.metadata.get("fatal") is not True:
                raise CheckFailed("the BUSY that refuses a connection must be fatal (§5.4)")
            if answer.request_id not in (0, 1):
                raise CheckFailed(
                    f"the BUSY that refuses a connection carries request id {answer.request_id}: "
                    "the HELLO's (1), or 0 before one arrived (§5.4)"
                )
            _check_retry_after(answer)
            peer.expect_closed()
            return f"connection {len(held)} refused: {_message(answer)}"
        raise CheckFailed(f"{limit + 1} connections were all served; max_connections is {limit}")
    finally:
        for peer in held:
            peer.close()
        _wait_for_a_free_slot(ctx)


def _check_retry_after(busy: Frame) -> None:
    """A BUSY's ``details.retry_after_ms``, when present, is an integer >= 1 (§6.1; a SHOULD,
    so its absence is no failure)."""
    details = busy.metadata.get("details")
    hint = details.get("retry_after_ms") if isinstance(details, dict) else None
    if hint is not None and not _positive_int(hint):
        raise CheckFailed(f"BUSY details.retry_after_ms is {hint!r}, not an integer >= 1 (§6.1)")


def _wait_for_a_free_slot(ctx: Context, timeout_s: float = 15.0) -> None:
    """After closing many connections, wait until the server serves a new one again, so that
    the checks after this one do not meet the limit this one reached."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with ctx.peer() as peer:
            peer.send(Hello(1, ((1, 0),), "cellvision-conformance", ctx.target.auth_token))
            answer = peer.recv_frame()
            if isinstance(answer, Frame) and answer.type == MessageType.WELCOME:
                return
        time.sleep(0.05)


# ----------------------------------------------------------------------------- operator calls

NOT_OFFERED = (ErrorCode.UNKNOWN_MESSAGE_TYPE, ErrorCode.UNEXPECTED_MESSAGE)
"""How a 1.1 server that offers no operator calls answers one (SPEC §6.6: optional)."""


@check(
    "operator_call",
    "§6.6",
    "OPERATOR_CALL with deadline_ms 300 is answered once: OPERATOR_ANSWER (a person answered) or "
    "DEADLINE_EXCEEDED, or UNKNOWN_MESSAGE_TYPE / UNEXPECTED_MESSAGE from a server that offers "
    "none (optional); the connection goes on; on a 1.0 connection it is UNKNOWN_MESSAGE_TYPE",
)
def _operator_call(ctx: Context) -> str:
    peer, _ = _open_1_1(ctx)
    with peer:
        call = OperatorCall(
            60,
            "cellvision-conformance check: nothing to do, this call expires by itself",
            OPERATOR_CHOICES,
            deadline_ms=300.0,
        )
        peer.send(call, version=V1_1)
        frame = peer.recv_frame()
        if frame is CLOSED:
            raise CheckFailed("the server closed the connection instead of answering")
        assert isinstance(frame, Frame)
        if frame.request_id != 60:
            raise CheckFailed(f"answer for id {frame.request_id}, expected 60")
        code = frame.metadata.get("code")
        if frame.type == T.OPERATOR_ANSWER:
            choice = frame.metadata.get("choice")
            if choice not in OPERATOR_CHOICES:
                raise CheckFailed(f"OPERATOR_ANSWER.choice is {choice!r}")
            for optional in ("by", "operator", "reason"):
                value = frame.metadata.get(optional)
                if value is not None and not isinstance(value, str):
                    raise CheckFailed(f"OPERATOR_ANSWER.{optional} is not a string: {value!r}")
            note = f"a person answered {choice!r}"
        elif frame.type == T.ERROR and code == ErrorCode.DEADLINE_EXCEEDED:
            note = "nobody answered: DEADLINE_EXCEEDED"
        elif frame.type == T.ERROR and code in {int(c) for c in NOT_OFFERED}:
            note = f"not offered ({frame.metadata.get('name')}), which §6.6 allows"
        else:
            raise CheckFailed(
                "expected OPERATOR_ANSWER, DEADLINE_EXCEEDED, UNKNOWN_MESSAGE_TYPE or "
                f"UNEXPECTED_MESSAGE, got type 0x{frame.type:04x} {frame.metadata}"
            )
        if frame.type == T.ERROR and frame.metadata.get("fatal"):
            raise CheckFailed(f"{frame.metadata.get('name')} must not be fatal here")
        _still_alive(peer, 61)
    with ctx.peer() as peer:
        _agreed(_hello(peer, ctx, (1, 0), request_id=62), (1, 0))
        peer.send(OperatorCall(63, "on a 1.0 connection", deadline_ms=300.0), version=(1, 0))
        peer.expect_error(ErrorCode.UNKNOWN_MESSAGE_TYPE, request_id=63, fatal=False)
        _still_alive(peer, 64)
    return note
