"""The server does what protocol/SPEC.md says where they used to disagree (issue 28).

Every check runs against the real server on loopback: the project's client for what it can
send, the conformance suite's blocking peer for frames a well-behaved client never sends.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from loopback import Gate, client_for, run, server_in_thread, wait_until

from protocol import (
    BadImage,
    DeadlineExceeded,
    ErrorCode,
    Hello,
    ImageEncoding,
    Inspect,
    InternalError,
    InvalidArgument,
    MessageType,
    Ping,
    UnknownInspection,
    payload_from_array,
)
from protocol.conformance.peer import Peer, Target
from protocol.frames import Frame
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import Intrinsics, RequestCamera, RequestCameraSettings
from vision_server.results import ResultLog
from vision_server.server import VisionServer
from vision_server.service import CellRuntime
from vision_server.service.builtin import MeanIntensityPresence

SIZE = (64, 48)
"""The image size (width, height) the test camera's intrinsics are for, in pixels."""


def _catalog(gate: Gate | None = None) -> Catalog:
    intrinsics = Intrinsics(SIZE[0], SIZE[1], 60.0, 60.0, 32.0, 24.0)
    inspections: list[Any] = [MeanIntensityPresence("bright", "tool", 0.0, 255.0)]
    if gate is not None:
        inspections.append(gate)
    return Catalog.build(
        [RequestCamera("tool", RequestCameraSettings(intrinsics=intrinsics))], inspections
    )


def _image(width: int = SIZE[0], height: int = SIZE[1]) -> np.ndarray:
    return np.full((height, width), 120, np.uint8)


def _peer(server: VisionServer) -> Peer:
    return Peer(Target("127.0.0.1", server.port, 10.0))


# ----------------------------------------------------------------------------- §6.3 logging


def test_requests_that_end_in_error_are_logged_as_error_rows(tmp_path: Path) -> None:
    """SPEC §6.3: a request for a known inspection that ends in ERROR is one row in the log,
    with its error; an unknown inspection has no row to be logged under."""
    log = ResultLog(tmp_path / "results.sqlite3")

    async def session(server: VisionServer) -> None:
        async with client_for(server) as client:
            with pytest.raises(BadImage):  # not the size the camera's intrinsics are for
                await client.inspect("bright", _image(32, 24))
            with pytest.raises(InvalidArgument):
                await client.inspect("bright", _image(), options={"no_such_option": 1})
            with pytest.raises(UnknownInspection):
                await client.inspect("nobody", _image())
            await client.inspect("bright", _image())

    with server_in_thread(_catalog(), results=log) as server:
        run(session(server))
        health = server.service.health()["result_log"]
    rows = log.query(newest_first=False)
    assert [(r.inspection, (r.error or "").split(":")[0]) for r in rows] == [
        ("bright", "BAD_IMAGE"),
        ("bright", "INVALID_ARGUMENT"),
        ("bright", ""),
    ]
    assert health["written"] == 3
    assert health["failed"] == 0
    log.close()


def test_a_request_given_up_at_its_deadline_is_one_error_row(tmp_path: Path) -> None:
    """The run goes on after DEADLINE_EXCEEDED; the log gets the request's error row, not a
    second row with the verdict nobody received."""
    gate = Gate(camera="tool")
    log = ResultLog(tmp_path / "results.sqlite3")

    async def session(server: VisionServer) -> None:
        async with client_for(server) as client:
            with pytest.raises(DeadlineExceeded):
                await client.inspect("gate", _image(), deadline_s=0.05)
            await wait_until(lambda: len(log.query()) == 1, "the error row")
            gate.release.set()
            await wait_until(lambda: gate.finished == 1, "the abandoned run ends")
            await client.inspect("bright", _image())  # after the run's end, in order

    with server_in_thread(_catalog(gate), results=log) as server:
        run(session(server))
    rows = log.query(newest_first=False)
    assert [r.inspection for r in rows] == ["gate", "bright"]
    assert (rows[0].error or "").startswith("DEADLINE_EXCEEDED")
    log.close()


# ----------------------------------------------------------------------------- image size


def test_an_image_of_another_size_than_the_camera_intrinsics_is_bad_image() -> None:
    """Measurements in mm and poses use the intrinsics: an image of another size is refused,
    naming both sizes, raw or compressed."""

    async def session(server: VisionServer) -> None:
        async with client_for(server) as client:
            for encoding in (None, ImageEncoding.PNG):
                with pytest.raises(BadImage) as info:
                    await client.inspect("bright", _image(80, 60), encoding=encoding)
                assert "80x60" in info.value.message
                assert "64x48" in info.value.message
            result = await client.inspect("bright", _image())
            assert result.passed

    with server_in_thread(_catalog()) as server:
        run(session(server))


# ----------------------------------------------------------------------------- §6.1 BUSY


def _retry_after(error: Frame) -> Any:
    return error.metadata.get("details", {}).get("retry_after_ms")


def test_busy_beyond_max_in_flight_carries_retry_after() -> None:
    gate = Gate(camera="tool")
    payload = payload_from_array(_image())
    with server_in_thread(_catalog(gate), max_in_flight=1) as server, _peer(server) as peer:
        peer.handshake()
        peer.send(Inspect(2, "gate", (payload,)))
        run(wait_until(lambda: gate.entered == 1, "the first request runs"))
        peer.send(Inspect(3, "gate", (payload,)))
        busy = peer.expect_error(ErrorCode.BUSY, request_id=3)
        hint = _retry_after(busy)
        assert isinstance(hint, int)
        assert hint >= 1
        gate.release.set()
        assert peer.expect(MessageType.RESULT, request_id=2).request_id == 2


def test_the_busy_that_refuses_a_connection_carries_the_hello_id_and_retry_after() -> None:
    with server_in_thread(_catalog(), max_connections=1) as server, _peer(server) as first:
        first.handshake()
        with _peer(server) as second:
            second.send(Hello(9, ((1, 1), (1, 0)), "second"))
            busy = second.expect_error(ErrorCode.BUSY, request_id=9, fatal=True)
            assert _retry_after(busy) == 1000
            second.expect_closed()


# ----------------------------------------------------------------------------- §4.3 details


def test_image_too_large_for_a_huge_raw_header_is_i_json_on_the_wire() -> None:
    """Two u32 sides multiply past 2**53 - 1: the pixel count is clamped, the sides are sent,
    and the project's own decoder (which refuses non-I-JSON) reads the ERROR."""
    side = 2**32 - 1
    desc = {"blob": 0, "encoding": "gray8", "width": side, "height": side}
    frame = Frame(MessageType.INSPECT, 4, {"inspection": "bright", "images": [desc]}, (b"",))
    with server_in_thread(_catalog()) as server, _peer(server) as peer:
        peer.handshake()
        peer.send_frame(frame)
        error = peer.expect_error(ErrorCode.IMAGE_TOO_LARGE, request_id=4, fatal=False)
        details = error.metadata["details"]
        assert details["pixels"] == 2**53 - 1
        assert (details["width"], details["height"]) == (side, side)
        peer.send(Inspect(5, "bright", (payload_from_array(_image()),)))
        peer.expect(MessageType.RESULT, request_id=5)


# ----------------------------------------------------------------------------- §5.1 HELLO


def test_a_hello_limit_below_the_welcome_is_a_non_fatal_invalid_argument() -> None:
    """SPEC §3.4, §5.1: ERROR is not bound by the client's max_frame_bytes (it is how the
    client learns the limit was too small); the handshake is then not complete, and a new
    HELLO without the limit gets WELCOME (the refused limit does not stay)."""
    with server_in_thread(_catalog()) as server, _peer(server) as peer:
        peer.send(Hello(1, ((1, 1),), "tiny", None, 24), (1, 1))
        error = peer.expect_error(ErrorCode.INVALID_ARGUMENT, request_id=1, fatal=False)
        assert error.metadata["details"]["max_size"] == 24
        assert error.metadata["details"]["size"] > 24
        peer.send(Hello(2, ((1, 1),), "default"), (1, 1))
        peer.expect(MessageType.WELCOME, request_id=2)
        peer.send(Ping(3), (1, 1))
        peer.expect(MessageType.PONG, request_id=3)


# ----------------------------------------------------------------------------- §4.1 depth

QR_POSE_CELL = """\
cameras:
  tool:
    source: request
    depth: true
    intrinsics: {width: 64, height: 48, fx: 60, fy: 60, cx: 32, cy: 24}
inspections:
  - {name: pose, type: qr_pose, camera: tool, side_m: 0.04}
  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}
"""


def test_depth_rules_of_the_role_table(tmp_path: Path) -> None:
    """SPEC §4.1: an inspection that needs depth and gets none is BAD_IMAGE (qr_pose with a
    configured code size too); a depth image for an inspection without depth is BAD_IMAGE."""
    config = tmp_path / "cell.yaml"
    config.write_text(QR_POSE_CELL)
    runtime = CellRuntime(config)
    depth = np.full((SIZE[1], SIZE[0]), 500, np.uint16)

    async def session(server: VisionServer) -> None:
        async with client_for(server) as client:
            with pytest.raises(BadImage, match="depth"):
                await client.inspect("pose", _image())
            with pytest.raises(BadImage, match="takes no depth"):
                await client.inspect("bright", _image(), depth=[depth])
            assert (await client.inspect("bright", _image())).passed

    try:
        with server_in_thread(runtime.catalog) as server:
            run(session(server))
    finally:
        runtime.close()


# ----------------------------------------------------------------------------- §6.3 a bug


@dataclass(frozen=True)
class Crashes:
    """An inspection with a bug: its request is INTERNAL_ERROR, and still a row in the log."""

    name: str = "crashes"
    camera: str = "tool"
    type: str = "presence"
    uses_depth: bool = False
    frames: int = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        raise ZeroDivisionError("a bug")


def test_a_request_that_hits_a_bug_is_an_internal_error_row(tmp_path: Path) -> None:
    log = ResultLog(tmp_path / "results.sqlite3")
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [Crashes()])

    async def session(server: VisionServer) -> None:
        async with client_for(server) as client:
            with pytest.raises(InternalError):
                await client.inspect("crashes", _image())

    with server_in_thread(catalog, results=log) as server:
        run(session(server))
    assert [(r.error or "").split(":")[0] for r in log.query()] == ["INTERNAL_ERROR"]
    log.close()


# ----------------------------------------------------------------------------- §8.2 fields


def test_a_1_0_connection_gets_stored_and_the_1_1_limits_too(tmp_path: Path) -> None:
    """SPEC §8.2: fields 1.1 added MAY go to a 1.0 client (it ignores what it does not know);
    §6.3's MUST for ``stored`` holds on every connection."""
    log = ResultLog(tmp_path / "results.sqlite3")
    with server_in_thread(_catalog(), results=log) as server, _peer(server) as peer:
        peer.send(Hello(1, ((1, 0),), "old"))
        welcome = peer.expect(MessageType.WELCOME, request_id=1)
        assert welcome.metadata["version"] == [1, 0]
        assert "max_connections" in welcome.metadata["limits"]
        peer.send(Inspect(2, "bright", (payload_from_array(_image()),)))
        result = peer.expect(MessageType.RESULT, request_id=2)
        assert result.metadata["stored"] is True
    log.close()
