"""Issue 13, holes 2-4: what an unauthenticated, silent, slow or greedy connection can make the
server hold, through real sockets as an attacker would send it.

- Before HELLO only a HELLO-sized frame is accepted, and a frame the state machine refuses is
  refused at its header, before its body is read (SPEC §3.1, §3.4).
- After HELLO a body is read only when the request can be served: a pool slot and room in the
  server-wide byte budget; otherwise BUSY at the header and the body is skipped unread.
- Idle connections, frames that never complete, connections stuck in the TLS handshake and
  clients that never read their answers are closed or dropped (timeouts announced in WELCOME).
- A reply is bounded by bytes: what the client said it accepts (HELLO max_frame_bytes) and the
  server's budget, checked before the frames are taken.

Process-level memory (peak RSS under these attacks) is measured by scripts/attack.py, run by
tests/test_reliability.py.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from certs import self_signed
from loopback import Gate, client_for, run, server_in_thread, wait_until

from protocol import (
    Capture,
    ErrorCode,
    FrameDecoder,
    Hello,
    ImageEncoding,
    Inspect,
    MessageType,
    Ping,
    payload_from_array,
)
from protocol.conformance import Target
from protocol.conformance.peer import Peer
from protocol.constants import HEADER_SIZE
from protocol.frames import encode_metadata
from robot_client import VisionClient
from vision_server import Catalog
from vision_server.cameras import (
    FolderCamera,
    FolderCameraSettings,
    RequestCamera,
    RequestCameraSettings,
)
from vision_server.server import VisionServer
from vision_server.service.builtin import MeanIntensityPresence

MiB = 1024 * 1024


def peer_for(server: VisionServer, **target: Any) -> Peer:
    return Peer(Target("127.0.0.1", server.port, timeout_s=10.0, **target))


def inspect_frame(request_id: int, side: int) -> bytes:
    """An INSPECT of the built-in ``brightness`` inspection with a side x side gray8 image."""
    image = np.full((side, side), 200, np.uint8)
    message = Inspect(request_id, "brightness", (payload_from_array(image),))
    return message.to_frame((1, 0)).serialize()


@pytest.fixture
def gate() -> Iterator[Gate]:
    g = Gate(report_shape=True)
    yield g
    g.release.set()


@pytest.fixture
def folder_catalog(tmp_path: Path) -> Catalog:
    """A server camera replaying three 1024x768 colour images (2.36 MB each, raw)."""
    for i, value in enumerate((50, 100, 150)):
        cv2.imwrite(str(tmp_path / f"img{i}.png"), np.full((768, 1024, 3), value, np.uint8))
    return Catalog.build(
        [
            RequestCamera("tool", RequestCameraSettings()),
            FolderCamera("fixed", FolderCameraSettings(tmp_path), base_dir=tmp_path),
        ],
        [MeanIntensityPresence("brightness", "tool", 64.0, 255.0)],
    )


# ----------------------------------------------------------------------------- before HELLO


def test_before_hello_a_request_is_refused_at_its_header_without_its_body() -> None:
    """An unauthenticated client announcing a 60 MiB INSPECT is refused as soon as the 24
    header bytes have arrived: the server never waits for (or buffers) the body."""
    with server_in_thread() as server, peer_for(server) as peer:
        frame = inspect_frame(7, 7900)  # 62.4 MB, just under the 64 MiB frame limit
        peer.send_raw(frame[:HEADER_SIZE])
        error = peer.expect_error(ErrorCode.NOT_AUTHENTICATED, request_id=7, fatal=True)
        assert "before the handshake" in error.metadata["message"]
        peer.expect_closed()


def test_before_hello_only_a_hello_sized_frame_is_accepted() -> None:
    with server_in_thread() as server, peer_for(server) as peer:
        hello = Hello(1, ((1, 0),), "x" * (128 * 1024)).to_frame((1, 0)).serialize()
        peer.send_raw(hello[:HEADER_SIZE])
        error = peer.expect_error(ErrorCode.FRAME_TOO_LARGE, request_id=1, fatal=True)
        assert error.metadata["details"]["max_size"] == 64 * 1024
        peer.expect_closed()


# ----------------------------------------------------------------------------- after HELLO


def test_a_body_beyond_the_servers_byte_budget_is_busy_at_its_header_and_skipped() -> None:
    with server_in_thread(max_buffered_bytes=4 * MiB) as server, peer_for(server) as peer:
        peer.handshake()
        frame = inspect_frame(2, 2900)  # 8.4 MB: more than the whole budget
        peer.send_raw(frame[:HEADER_SIZE])
        # Answered before a single body byte was sent.
        busy = peer.expect_error(ErrorCode.BUSY, request_id=2, fatal=False)
        assert "memory for request bodies" in busy.metadata["message"]
        # The body is read and dropped, and the stream goes on at the next frame.
        peer.send_raw(frame[HEADER_SIZE:])
        peer.send(Ping(3, "after"))
        assert peer.expect(MessageType.PONG, request_id=3).metadata["data"] == "after"
        # A frame that fits is served, and what it held is given back.
        peer.send_raw(inspect_frame(4, 1000))
        peer.expect(MessageType.RESULT, request_id=4)
        budget = server.service.budget
        assert budget.peak <= budget.limit
        run(wait_until(lambda: budget.used == 0, "the budget is given back"))


def test_the_byte_budget_is_shared_by_all_connections() -> None:
    """Two connections each half-way through a 3 MB body: with a 4 MiB budget only the first
    is read; the second is BUSY at its header."""
    with (
        server_in_thread(max_buffered_bytes=4 * MiB) as server,
        peer_for(server) as first,
        peer_for(server) as second,
    ):
        first.handshake()
        second.handshake()
        frame_a, frame_b = inspect_frame(2, 1800), inspect_frame(2, 1800)  # 3.2 MB each
        first.send_raw(frame_a[: len(frame_a) // 2])
        run(wait_until(lambda: server.service.budget.used > 0, "the first body is admitted"))
        second.send_raw(frame_b[:HEADER_SIZE])
        second.expect_error(ErrorCode.BUSY, request_id=2)
        first.send_raw(frame_a[len(frame_a) // 2 :])
        first.expect(MessageType.RESULT, request_id=2)
        assert server.service.budget.peak <= 4 * MiB


def test_an_inspect_with_no_free_slot_waits_unread_then_runs(gate: Gate) -> None:
    """Backpressure, not BUSY: while no worker slot is free the server stops reading the
    connection at the request's metadata (its image stays in the socket), and runs it once a
    slot is free; nothing is refused."""
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [gate])
    with (
        server_in_thread(catalog, workers=1, queue_depth=0, fast_workers=0) as server,
        peer_for(server) as peer,
        peer_for(server) as other,
    ):
        peer.handshake()
        other.handshake()
        image = payload_from_array(np.zeros((600, 600), np.uint8))
        peer.send(Inspect(2, "gate", (image,)))
        run(wait_until(lambda: gate.entered == 1, "the first request runs"))
        other.send(Inspect(3, "gate", (image,)))
        run(wait_until(lambda: server.service.pool.waiting == 1, "the second one waits"))
        # Its image is not in the server's memory: at most one read's worth of it.
        assert max(s.conn.buffered_bytes for s in server.tcp.connections) < 600 * 600
        gate.release.set()
        peer.expect(MessageType.RESULT, request_id=2)
        other.expect(MessageType.RESULT, request_id=3)
        assert server.service.busy_count == 0
        run(wait_until(lambda: server.service.pool.admitted == 0, "the worker slot is given back"))


def test_a_request_that_waits_too_long_for_a_slot_is_busy_with_a_retry_after(gate: Gate) -> None:
    """After admission_wait_s without a slot: BUSY with retry_after_ms, answered before the
    image was sent (header and metadata only); the body is then skipped and the stream goes
    on."""
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [gate])
    with (
        server_in_thread(
            catalog, workers=1, queue_depth=0, fast_workers=0, admission_wait_s=0.0
        ) as server,
        peer_for(server) as peer,
        peer_for(server) as other,
    ):
        peer.handshake()
        other.handshake()
        image = payload_from_array(np.zeros((600, 600), np.uint8))
        peer.send(Inspect(2, "gate", (image,)))
        run(wait_until(lambda: gate.entered == 1, "the first request runs"))
        frame = Inspect(3, "gate", (image,)).to_frame((1, 1))
        second = frame.serialize()
        up_to_metadata = HEADER_SIZE + len(encode_metadata(frame.metadata))
        other.send_raw(second[:up_to_metadata])
        busy = other.expect_error(ErrorCode.BUSY, request_id=3, fatal=False)
        assert busy.metadata["details"]["retry_after_ms"] >= 1
        other.send_raw(second[up_to_metadata:])
        other.send(Ping(4, "after"))
        assert other.expect(MessageType.PONG, request_id=4).metadata["data"] == "after"
        gate.release.set()
        peer.expect(MessageType.RESULT, request_id=2)
        run(wait_until(lambda: server.service.pool.admitted == 0, "the worker slot is given back"))


# ----------------------------------------------------------------------------- timeouts


def test_welcome_announces_the_timeouts() -> None:
    with (
        server_in_thread(idle_timeout_s=12.5, frame_timeout_s=7.0) as server,
        peer_for(server) as peer,
    ):
        limits = peer.handshake().metadata["limits"]
        assert limits["idle_timeout_ms"] == 12500
        assert limits["frame_timeout_ms"] == 7000


def test_an_idle_connection_is_closed_after_the_handshake() -> None:
    with server_in_thread(idle_timeout_s=0.3) as server, peer_for(server) as peer:
        peer.handshake()
        close = peer.expect(MessageType.CLOSE, timeout_s=20.0)
        assert "idle" in close.metadata["reason"]
        peer.expect_closed(timeout_s=20.0)
        run(wait_until(lambda: not server.tcp.connections, "the slot is free"))


def test_a_frame_that_never_completes_is_closed() -> None:
    with server_in_thread(frame_timeout_s=0.3) as server, peer_for(server) as peer:
        peer.handshake()
        frame = Ping(2, "half a frame").to_frame((1, 0)).serialize()
        peer.send_raw(frame[: len(frame) - 3])
        close = peer.expect(MessageType.CLOSE, timeout_s=20.0)
        assert "not complete" in close.metadata["reason"]
        peer.expect_closed(timeout_s=20.0)


def test_the_robot_client_keeps_an_idle_connection_alive() -> None:
    pings: list[int] = []

    class Counting(VisionClient):
        async def request(self, build: Any, *, timeout_s: float | None = None) -> Any:
            message = build(0)
            if isinstance(message, Ping) and message.data == "keepalive":
                pings.append(1)
            return await super().request(build, timeout_s=timeout_s)

    async def body(server: VisionServer) -> None:
        async with Counting("127.0.0.1", server.port) as client:
            first = client._conn
            await wait_until(lambda: len(pings) >= 4, "keepalive pings", timeout_s=30.0)
            assert client._conn is first  # never closed as idle, never reconnected
            assert client.reconnects == 0
            assert await client.ping() >= 0.0

    with server_in_thread(idle_timeout_s=1.5) as server:
        run(body(server), timeout_s=60.0)


def test_connections_in_the_tls_handshake_count_and_time_out(tmp_path: Path) -> None:
    """A TCP connection that never starts TLS holds a connection slot only until the handshake
    timeout; while it holds it, the server is full."""
    cert, key = self_signed(tmp_path)
    settings = {"tls_cert": str(cert), "tls_key": str(key)}
    with server_in_thread(max_connections=1, handshake_timeout_s=0.5, **settings) as server:
        silent = socket.create_connection(("127.0.0.1", server.port), timeout=20.0)
        try:
            run(wait_until(lambda: len(server.tcp.connections) == 1, "the silent one is counted"))
            with peer_for(server, tls=True, tls_verify=False) as refused:
                refused.send(Hello(1))
                refused.expect_error(ErrorCode.BUSY, request_id=1, fatal=True)
            assert silent.recv(1024) == b""  # closed by the server at the handshake timeout
        finally:
            silent.close()
        run(wait_until(lambda: not server.tcp.connections, "the slot is free"))
        with peer_for(server, tls=True, tls_verify=False) as peer:
            peer.handshake()
            peer.send(Ping(2))
            peer.expect(MessageType.PONG, request_id=2)


def test_a_client_that_never_reads_its_answers_is_dropped() -> None:
    big = "x" * 65536
    with server_in_thread(write_timeout_s=0.5) as server:
        slow = socket.socket()
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        slow.connect(("127.0.0.1", server.port))
        try:
            slow.sendall(Hello(1).to_frame((1, 0)).serialize())
            decoder = FrameDecoder()
            while (welcome := decoder.next_frame()) is None:
                decoder.feed(slow.recv(65536))
            assert welcome.type == MessageType.WELCOME
            slow.setblocking(False)
            for i in range(64):  # 4 MiB of PONGs to echo; the server gives up on us first
                with_data = Ping(2 + i, big).to_frame((1, 0)).serialize()
                try:
                    slow.send(with_data)
                except (BlockingIOError, ConnectionError):
                    break
            run(wait_until(lambda: not server.tcp.connections, "the slow reader is dropped", 30.0))
        finally:
            slow.close()
        with peer_for(server) as peer:
            peer.handshake()
            peer.send(Ping(2, "still serving"))
            peer.expect(MessageType.PONG, request_id=2)


# ----------------------------------------------------------------------------- replies


def test_a_capture_larger_than_the_client_accepts_is_refused_before_it_is_taken(
    folder_catalog: Catalog,
) -> None:
    with server_in_thread(folder_catalog) as server, peer_for(server) as peer:
        peer.send(Hello(1, ((1, 0),), "small", None, 1 * MiB))
        peer.expect(MessageType.WELCOME, request_id=1)
        peer.send(Capture(2, "fixed", count=1))
        error = peer.expect_error(ErrorCode.INVALID_ARGUMENT, request_id=2)
        assert error.metadata["details"]["max_size"] == 1 * MiB
        assert "HELLO max_frame_bytes" in error.metadata["message"]
        # A compressed encoding fits, and is checked once encoded.
        peer.send(Capture(3, "fixed", count=1, encoding=ImageEncoding.PNG))
        peer.expect(MessageType.FRAMES, request_id=3)


def test_a_client_without_max_frame_bytes_gets_the_protocol_default(
    folder_catalog: Catalog,
) -> None:
    with server_in_thread(folder_catalog) as server, peer_for(server) as peer:
        peer.handshake()
        peer.send(Capture(2, "fixed", count=30))  # 70.8 MB raw: over the 64 MiB default
        error = peer.expect_error(ErrorCode.INVALID_ARGUMENT, request_id=2)
        assert error.metadata["details"]["max_size"] == 64 * MiB


def test_the_robot_client_receives_a_capture_of_thirty_frames(folder_catalog: Catalog) -> None:
    """30 raw 1024x768 frames (70.8 MB): the robot client says it accepts more than 64 MiB."""

    async def body(server: VisionServer) -> None:
        async with client_for(server) as client:
            frames = await client.capture("fixed", count=30)
            assert len(frames.images) == 30

    with server_in_thread(folder_catalog) as server:
        run(body(server), timeout_s=120.0)
        run(wait_until(lambda: server.service.budget.used == 0, "the reply's bytes are given back"))


def test_pipelined_captures_that_are_never_read_stay_within_the_budget(
    folder_catalog: Catalog,
) -> None:
    """12 pipelined CAPTUREs of 20 frames (47 MB each) from a client that never reads: the
    replies the server builds stay within its budget; the rest are BUSY, not queued."""
    budget = 64 * MiB
    with server_in_thread(folder_catalog, max_buffered_bytes=budget) as server:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect(("127.0.0.1", server.port))
        try:
            sock.sendall(Hello(1).to_frame((1, 0)).serialize())
            sock.sendall(
                b"".join(
                    Capture(2 + i, "fixed", count=20).to_frame((1, 0)).serialize()
                    for i in range(12)
                )
            )
            # The first reply waits in the socket for a reader that never comes; every other
            # CAPTURE finds the budget taken.
            run(wait_until(lambda: server.service.budget.refused == 11, "11 BUSY", 60.0))
            assert server.service.budget.peak <= budget
            # Nothing waits in the pool behind the stuck reply.
            run(wait_until(lambda: server.service.pool.admitted == 0, "the workers are free"))
        finally:
            sock.close()
        run(wait_until(lambda: server.service.budget.used == 0, "everything is given back", 60.0))
