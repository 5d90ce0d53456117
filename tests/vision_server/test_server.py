"""Loopback integration tests of the asyncio server: admission (BUSY), shutdown, isolation.

Each test starts a real VisionServer on 127.0.0.1, port 0. Tests that drive it with blocking
sockets run it on an event loop in a background thread; the others run it on the test's loop.
"""

from __future__ import annotations

import asyncio
import logging
import select
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from loopback import Gate, client_for, run, server_in_thread, wait_until

from protocol import (
    Busy,
    CameraUnavailable,
    DeadlineExceeded,
    ErrorCode,
    Frame,
    FrameDecoder,
    Hello,
    Inspect,
    InternalError,
    InvalidArgument,
    MessageType,
    Ping,
    ShuttingDown,
    UnknownCamera,
    payload_from_array,
)
from protocol.conformance import Target
from protocol.conformance.peer import CLOSED, Peer
from robot_client.client import ReconnectPolicy
from robot_client.errors import ConnectionLost
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import (
    FolderCamera,
    FolderCameraSettings,
    RequestCamera,
    RequestCameraSettings,
)
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import core as service_module
from vision_server.service.builtin import MeanIntensityPresence, builtin_catalog
from vision_server.service.core import InspectionRecord, encode_image

T = TypeVar("T")
GRAY = np.full((48, 64), 200, np.uint8)


@dataclass(frozen=True)
class Raises:
    name: str = "raises"
    camera: str = "tool"
    type: str = "presence"
    uses_depth: bool = False
    frames: int = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        raise ZeroDivisionError("a bug in the inspection")


@dataclass(frozen=True)
class NumpyData:
    """Returns numpy scalars and NaN in its data, which JSON cannot carry as they are."""

    name: str = "numpy_data"
    camera: str = "tool"
    type: str = "presence"
    uses_depth: bool = False
    frames: int = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        return InspectionOutcome(True, {"count": np.int64(3), "score": float("nan")})


def make_catalog(*extra: Any) -> Catalog:
    return Catalog.build(
        [
            RequestCamera("tool", RequestCameraSettings()),
            FolderCamera(
                "fixed", FolderCameraSettings(Path("no-such-folder")), base_dir=Path("/nonexistent")
            ),
        ],
        [MeanIntensityPresence("brightness", "tool", 64.0, 255.0), *extra],
    )


@pytest.fixture
def gate() -> Iterator[Gate]:
    g = Gate(report_shape=True)
    yield g
    g.release.set()  # never leave a worker thread blocked behind a failed test


def open_peer(server: VisionServer) -> Peer:
    peer = Peer(Target("127.0.0.1", server.port, timeout_s=10.0))
    peer.handshake()
    return peer


# ----------------------------------------------------------------------------- admission


def test_full_pool_answers_busy_and_the_admitted_request_still_completes(gate: Gate) -> None:
    async def body() -> None:
        # admission_wait_s 0: BUSY at once instead of waiting unread (test_hardening.py).
        settings = ServerSettings(port=0, workers=1, queue_depth=0, admission_wait_s=0.0)
        async with (
            VisionServer(make_catalog(gate), settings) as server,
            client_for(server) as client,
            client_for(server) as other,
        ):
            # One slot in all: WELCOME says so, and this client keeps to it.
            assert client.welcome is not None
            assert client.welcome.limits["max_in_flight"] == 1
            first = asyncio.create_task(client.inspect("gate", GRAY))
            await wait_until(lambda: gate.entered == 1, "the gate inspection started")
            with pytest.raises(Busy) as busy:  # another client finds the pool full
                await other.inspect("brightness", GRAY)
            assert busy.value.code is ErrorCode.BUSY
            assert busy.value.fatal is False
            assert busy.value.request_id != 0
            # PING does not need a worker: it is answered while the pool is full.
            assert await other.ping() >= 0.0
            gate.release.set()
            result = await first
            assert result.passed
            assert result.data == {"shape": [48, 64]}
            # The slot is free again.
            assert (await client.inspect("brightness", GRAY)).passed
            assert client.reconnects == 0

    run(body())


def test_requests_beyond_max_in_flight_on_one_connection_are_busy(gate: Gate) -> None:
    with (
        server_in_thread(make_catalog(gate), max_in_flight=2, workers=3) as server,
        open_peer(server) as peer,
    ):
        image = (payload_from_array(GRAY),)
        peer.send_raw(
            b"".join(
                Inspect(rid, "gate", image).to_frame((1, 0)).serialize() for rid in (11, 12, 13)
            )
        )
        busy = peer.expect_error(ErrorCode.BUSY, request_id=13, fatal=False)
        assert "2" in busy.metadata["message"]
        # The limit is per connection: another one still gets its requests run.
        with open_peer(server) as other:
            other.send(Inspect(21, "brightness", image))
            assert other.expect(MessageType.RESULT, request_id=21).metadata["verdict"] == "pass"
        gate.release.set()
        answered = {peer.expect(MessageType.RESULT).request_id for _ in range(2)}
        assert answered == {11, 12}
        assert gate.entered == 2


def test_max_connections_refuses_with_busy() -> None:
    async def body() -> None:
        async with VisionServer(builtin_catalog(), ServerSettings(port=0, max_connections=1)) as s:
            first = client_for(s)
            await first.connect()
            refused = client_for(s, reconnect=ReconnectPolicy(attempts=0))
            with pytest.raises(Busy):
                await refused.connect()
            # The connection that was admitted is unaffected.
            assert await first.ping() >= 0.0
            await first.close()

            # Once it is gone, a new client gets in (the server frees the slot asynchronously).
            async def connects() -> bool:
                late = client_for(s, reconnect=ReconnectPolicy(attempts=0))
                try:
                    await late.connect()
                except Busy:
                    return False
                await late.close()
                return True

            for _ in range(500):
                if await connects():
                    break
                await asyncio.sleep(0.02)
            else:
                pytest.fail("the freed connection slot never went to a new client")

    run(body())


# ----------------------------------------------------------------------------- failures


def test_an_inspection_that_raises_is_internal_error_and_the_connection_survives() -> None:
    async def body() -> None:
        async with (
            VisionServer(make_catalog(Raises()), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            with pytest.raises(InternalError) as caught:
                await client.inspect("raises", GRAY)
            assert "ZeroDivisionError" in caught.value.message
            assert caught.value.fatal is False
            assert (await client.inspect("brightness", GRAY)).passed
            assert client.reconnects == 0

    run(body())


def test_a_result_json_cannot_carry_is_internal_error_and_the_connection_survives() -> None:
    async def body() -> None:
        async with (
            VisionServer(make_catalog(NumpyData()), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            other = asyncio.create_task(client.inspect("brightness", GRAY))
            with pytest.raises(InternalError):
                await client.inspect("numpy_data", GRAY)
            assert (await other).passed
            assert await client.ping() >= 0.0
            assert client.reconnects == 0

    run(body())


def test_deadline_exceeded_while_the_work_goes_on(gate: Gate) -> None:
    async def body() -> None:
        async with (
            VisionServer(make_catalog(gate), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            with pytest.raises(DeadlineExceeded) as caught:
                await client.inspect("gate", GRAY, deadline_s=0.05)
            assert caught.value.fatal is False
            assert await client.ping() >= 0.0
            gate.release.set()
            assert (await client.inspect("gate", GRAY, deadline_s=10.0)).passed

    run(body())


def test_request_id_zero_is_answered_by_a_connection_level_error() -> None:
    with server_in_thread(builtin_catalog()) as server, open_peer(server) as peer:
        peer.send_frame(Frame(MessageType.PING, 0))
        peer.expect_error(ErrorCode.UNEXPECTED_MESSAGE, request_id=0, fatal=False)
        peer.send(Ping(2, "still here"))
        assert peer.expect(MessageType.PONG, request_id=2).metadata["data"] == "still here"


def test_capture_errors() -> None:
    async def body() -> None:
        async with (
            VisionServer(make_catalog(), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            with pytest.raises(InvalidArgument):
                await client.capture("tool")
            with pytest.raises(UnknownCamera):
                await client.capture("nope")
            with pytest.raises(CameraUnavailable):
                await client.capture("fixed")

    run(body())


def test_overlays_are_encoded_in_the_worker_pool(monkeypatch: pytest.MonkeyPatch) -> None:
    encoded_in: list[str] = []

    def recording(*args: Any, **kwargs: Any) -> Any:
        encoded_in.append(threading.current_thread().name)
        return encode_image(*args, **kwargs)

    monkeypatch.setattr(service_module, "encode_image", recording)

    async def body() -> None:
        async with (
            VisionServer(builtin_catalog(), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            result = await client.inspect("brightness", GRAY, overlay=True)
            assert len(result.images) == 1
            # CPU work on the event loop would stall every connection meanwhile.
            assert encoded_in
            assert threading.current_thread().name not in encoded_in
            assert all(name.startswith("inspect") for name in encoded_in)

    run(body())


# ----------------------------------------------------------------------------- lifecycle


def test_stop_answers_unfinished_requests_with_shutting_down(gate: Gate) -> None:
    async def body() -> None:
        settings = ServerSettings(port=0, shutdown_grace_s=0.2, workers=3)
        server = VisionServer(make_catalog(gate), settings)
        await server.start()
        port = server.port
        client = client_for(server, reconnect=ReconnectPolicy(attempts=1, initial_s=0.01))
        await client.connect()
        tasks = [asyncio.create_task(client.inspect("gate", GRAY)) for _ in range(3)]
        await wait_until(lambda: gate.entered == 3, "three inspections running")
        await server.stop()
        outcomes = await asyncio.gather(*tasks, return_exceptions=True)
        assert [type(o) for o in outcomes] == [ShuttingDown] * 3
        gate.release.set()
        # Nothing listens any more: the next request cannot reconnect.
        with pytest.raises(ConnectionLost):
            await client.ping()
        with socket.socket() as probe:
            assert probe.connect_ex(("127.0.0.1", port)) != 0
        await client.close()

    run(body())


def test_stop_lets_requests_finish_within_the_grace_period(gate: Gate) -> None:
    async def body() -> None:
        server = VisionServer(make_catalog(gate), ServerSettings(port=0, shutdown_grace_s=10.0))
        await server.start()
        client = client_for(server, reconnect=ReconnectPolicy(attempts=0))
        await client.connect()
        task = asyncio.create_task(client.inspect("gate", GRAY))
        await wait_until(lambda: gate.entered == 1, "the inspection started")
        stopping = asyncio.create_task(server.stop())
        await asyncio.sleep(0)  # stop() has begun: no more connections are accepted
        gate.release.set()
        assert (await task).passed
        await stopping
        await client.close()

    run(body())


def test_replace_catalog_serves_new_requests_with_the_new_one() -> None:
    async def body() -> None:
        records: list[InspectionRecord] = []
        async with VisionServer(builtin_catalog(), ServerSettings(port=0)) as server:
            server.service.subscribe(records.append)
            async with client_for(server) as client:
                before = await client.inspect("brightness", GRAY)
                server.replace_catalog(make_catalog(Raises()))
                names = {i["name"] for i in await client.list_inspections()}
                assert names == {"brightness", "raises"}
                after = await client.inspect("brightness", GRAY)
                assert before.config_hash != after.config_hash
        assert [r.reply.config_hash for r in records] == [before.config_hash, after.config_hash]

    run(body())


# ----------------------------------------------------------------------------- isolation


def _push_until_stuck(sock: socket.socket, chunks: Iterator[bytes], stall_s: float) -> int:
    """Send ``chunks`` without ever reading; stop once the peer accepts nothing for stall_s."""
    sock.setblocking(False)
    sent = 0
    for chunk in chunks:
        view = memoryview(chunk)
        while view:
            _, writable, _ = select.select([], [sock], [], stall_s)
            if not writable:
                return sent
            n = sock.send(view)
            sent += n
            view = view[n:]
    return sent


def test_a_client_that_never_reads_does_not_hold_up_the_others(
    caplog: pytest.LogCaptureFixture,
) -> None:
    big = "x" * 65536
    count = 1024  # 64 MiB of PINGs whose PONGs echo the same 64 KiB back
    with server_in_thread(builtin_catalog()) as server:
        slow = socket.create_connection(("127.0.0.1", server.port), timeout=10.0)
        try:
            slow.sendall(Hello(1).to_frame((1, 0)).serialize())
            decoder = FrameDecoder()
            while (welcome := decoder.next_frame()) is None:
                decoder.feed(slow.recv(65536))
            assert welcome.type == MessageType.WELCOME
            frames = (Ping(2 + i, big).to_frame((1, 0)).serialize() for i in range(count))
            sent = _push_until_stuck(slow, frames, stall_s=1.0)
            # The server stopped reading from it (backpressure) instead of buffering it all.
            assert sent < count * len(big)

            async def other_client() -> None:
                async with client_for(server) as client:
                    for _ in range(5):
                        assert await client.ping() >= 0.0
                    result = await client.inspect("brightness", GRAY, overlay=True)
                    assert result.passed
                    assert len(result.images) == 1

            run(other_client())
        finally:
            slow.close()
        # The stuck connection is dropped cleanly; the server goes on serving.
        with open_peer(server) as peer:
            peer.send(Ping(5, "after"))
            assert peer.expect(MessageType.PONG, request_id=5).metadata["data"] == "after"
    # Its reset is logged as a lost connection, not as a server error with a traceback.
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


def test_garbage_on_one_connection_closes_only_that_one() -> None:
    with (
        server_in_thread(builtin_catalog()) as server,
        open_peer(server) as good,
        open_peer(server) as bad,
    ):
        bad.send_raw(b"\x00" * 64)
        bad.expect_error(ErrorCode.MALFORMED_FRAME, fatal=True)
        assert bad.recv_frame() is CLOSED
        good.send(Ping(3, "ok"))
        assert good.expect(MessageType.PONG, request_id=3).metadata["data"] == "ok"
