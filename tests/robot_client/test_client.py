"""Loopback integration tests of the asyncio client against the real server (and scripted fakes).

Every server listens on 127.0.0.1, port 0. Async bodies run under ``run`` (no pytest-asyncio).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import subprocess
import sys
import threading
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from loopback import Gate, client_for, run, wait_until

from protocol import (
    BadImage,
    Close,
    Error,
    ErrorCode,
    Frame,
    FrameDecoder,
    ImageEncoding,
    ImagePayload,
    ImageRole,
    ImageTooLarge,
    MessageType,
    NotAuthenticated,
    Ping,
    Pong,
    ShuttingDown,
    State,
    UnknownInspection,
    UnsupportedVersion,
    Welcome,
    payload_from_array,
)
from robot_client.client import (
    ReconnectPolicy,
    SyncVisionClient,
    VisionClient,
    overlay_image,
    wait_for_server,
)
from robot_client.errors import ClientClosed, ConnectionLost, NotCellvision, RequestTimeout
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import (
    RequestCamera,
    RequestCameraSettings,
)
from vision_server.server import ServerSettings, VisionServer
from vision_server.service.builtin import MeanIntensityPresence, builtin_catalog

T = TypeVar("T")
REPO_ROOT = Path(__file__).resolve().parents[2]
GRAY = np.full((48, 64), 200, np.uint8)


@dataclass(eq=False)
class Counting:
    """Counts its runs: tells whether a request reached the server (once, or twice)."""

    name: str = "stall"
    camera: str = "tool"
    type: str = "presence"
    uses_depth: bool = False
    frames: int = 1
    runs: int = 0

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        self.runs += 1
        return InspectionOutcome(True, {"runs": self.runs})


def make_catalog(*extra: Any) -> Catalog:
    return Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [MeanIntensityPresence("brightness", "tool", 64.0, 255.0), *extra],
    )


@pytest.fixture
def gate() -> Iterator[Gate]:
    g = Gate()
    yield g
    g.release.set()


def free_port_nobody_listens_on() -> tuple[socket.socket, int]:
    """A port bound but not listening: connecting to it is refused for as long as we hold it."""
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    return holder, holder.getsockname()[1]


# ----------------------------------------------------------------------------- basics


def test_handshake_ping_and_list() -> None:
    async def body() -> None:
        async with VisionServer(builtin_catalog(), ServerSettings(port=0)) as server:
            client = client_for(server)
            assert not client.connected
            welcome = await client.connect()
            assert client.connected
            assert welcome.version == (1, 1)
            assert welcome.server_name == "cellvision"
            # What a client can count on: the connection's limit, bounded by the pool's slots.
            settings = server.settings
            assert welcome.limits["max_in_flight"] == min(
                settings.max_in_flight, settings.workers + settings.queue_depth
            )
            assert [i["name"] for i in welcome.inspections] == ["brightness"]
            assert welcome.cameras == ({"name": "tool", "source": "request", "depth": False},)
            assert await client.connect() is welcome  # already connected: no new handshake
            assert await client.ping() >= 0.0
            pong = await client.request(lambda rid: Ping(rid, "echo me"))
            assert isinstance(pong, Pong)
            assert pong.data == "echo me"
            listed = await client.list_inspections()
            assert listed == welcome.inspections
            await client.close()
            assert not client.connected
            with pytest.raises(ClientClosed):
                await client.ping()

    run(body())


@pytest.mark.parametrize(
    ("image", "encoding", "mean"),
    [
        (np.full((48, 64), 200, np.uint8), None, 200.0),
        (np.dstack([np.full((48, 64), v, np.uint8) for v in (100, 150, 200)]), None, 150.0),
        (np.full((48, 64), 30, np.uint8), ImageEncoding.PNG, 30.0),
        (np.full((48, 64, 3), 120, np.uint8), ImageEncoding.JPEG, 120.0),
    ],
    ids=["gray8", "bgr8", "png", "jpeg"],
)
def test_inspect_each_encoding(
    image: np.ndarray, encoding: ImageEncoding | None, mean: float
) -> None:
    async def body() -> None:
        async with (
            VisionServer(builtin_catalog(), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            result = await client.inspect("brightness", image, encoding=encoding)
        assert result.inspection == "brightness"
        assert result.camera == "tool"
        assert result.config_hash == builtin_catalog().config_hash
        assert result.data["measure"] == "mean_intensity"
        assert result.data["value"] == pytest.approx(mean, abs=1.0)
        assert result.passed is (64.0 <= mean <= 255.0)
        assert set(result.timing) == {"compute_ms", "total_ms"}
        assert result.images == ()
        assert overlay_image(result) is None

    run(body())


def test_overlay_image_comes_back() -> None:
    gradient = np.tile(np.arange(64, dtype=np.uint8) * 4, (48, 1))

    async def body() -> None:
        async with (
            VisionServer(builtin_catalog(), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            result = await client.inspect("brightness", gradient, overlay=True)
        assert len(result.images) == 1
        assert result.images[0].role is ImageRole.OVERLAY
        assert result.images[0].encoding is ImageEncoding.PNG
        overlay = overlay_image(result)
        assert overlay is not None
        # The built-in inspection's overlay is its input; PNG is lossless.
        np.testing.assert_array_equal(overlay, gradient)

    run(body())


def test_server_errors_are_rebuilt_as_their_classes() -> None:
    async def body() -> None:
        settings = ServerSettings(port=0, max_image_pixels=1000)
        async with (
            VisionServer(builtin_catalog(), settings) as server,
            client_for(server) as client,
        ):
            with pytest.raises(UnknownInspection) as unknown:
                await client.inspect("no-such", np.zeros((8, 8), np.uint8))
            assert unknown.value.code is ErrorCode.UNKNOWN_INSPECTION
            assert unknown.value.request_id != 0
            assert not unknown.value.fatal
            assert "no-such" in unknown.value.message
            with pytest.raises(BadImage, match="has none"):
                await client.inspect("brightness")  # a request camera needs images
            png = payload_from_array(np.zeros((8, 8), np.uint8), encoding=ImageEncoding.PNG)
            wrong_size = ImagePayload(ImageEncoding.PNG, 9, 8, png.data)
            with pytest.raises(BadImage):
                await client.inspect("brightness", wrong_size)
            with pytest.raises(BadImage, match="no depth"):
                await client.inspect(
                    "brightness",
                    np.zeros((8, 8), np.uint8),
                    depth=[np.zeros((8, 8), np.uint16)],
                )
            with pytest.raises(ImageTooLarge) as too_large:
                await client.inspect("brightness", GRAY)  # 3072 pixels > 1000
            assert too_large.value.details == {
                "pixels": 3072,
                "width": 64,
                "height": 48,
                "max_pixels": 1000,
            }
            # Every one of them was non-fatal: still the first connection.
            assert (await client.inspect("brightness", np.full((8, 8), 99, np.uint8))).passed
            assert client.reconnects == 0

    run(body())


def test_fifty_pipelined_requests_are_matched_by_id() -> None:
    async def body() -> None:
        settings = ServerSettings(port=0, workers=2, queue_depth=16)
        async with (
            VisionServer(builtin_catalog(), settings) as server,
            client_for(server) as client,
        ):
            jobs: list[tuple[str, Any, Awaitable[Any]]] = []
            for i in range(50):
                if i % 3 == 0:
                    level = 70 + i  # each image has its own mean
                    image = np.full((240, 320), level, np.uint8)
                    jobs.append(("inspect", float(level), client.inspect("brightness", image)))
                elif i % 3 == 1:
                    data = f"ping-{i}"
                    jobs.append(("ping", data, client.request(lambda r, d=data: Ping(r, d))))
                else:
                    jobs.append(("list", None, client.list_inspections()))
            answers = await asyncio.gather(*(job for _, _, job in jobs))
            for (kind, expected, _), answer in zip(jobs, answers, strict=True):
                if kind == "inspect":
                    assert answer.data["value"] == expected
                elif kind == "ping":
                    assert answer.data == expected
                else:
                    assert [i["name"] for i in answer] == ["brightness"]
            assert sum(kind == "inspect" for kind, _, _ in jobs) == 17
            assert client.reconnects == 0

    run(body())


def test_the_client_keeps_within_the_servers_max_in_flight(gate: Gate) -> None:
    async def body() -> None:
        settings = ServerSettings(port=0, max_in_flight=2, workers=4)
        async with (
            VisionServer(make_catalog(gate), settings) as server,
            client_for(server) as client,
        ):
            tasks = [asyncio.create_task(client.inspect("gate", GRAY)) for _ in range(5)]
            await wait_until(lambda: gate.entered == 2, "two inspections running")
            # The other three wait on the client's side instead of being refused BUSY.
            with pytest.raises(RequestTimeout, match="max_in_flight"):
                await client.inspect("brightness", GRAY, timeout_s=0.2)
            assert not any(task.done() for task in tasks)
            gate.release.set()
            results = await asyncio.gather(*tasks)
            assert [r.data for r in results] == [{"gate": True}] * 5
            assert gate.entered == 5

    run(body())


# ----------------------------------------------------------------------------- timeouts


def test_request_timeout_then_the_late_answer_is_dropped(gate: Gate) -> None:
    async def body() -> None:
        async with (
            VisionServer(make_catalog(gate), ServerSettings(port=0)) as server,
            client_for(server) as client,
        ):
            with pytest.raises(RequestTimeout):
                await client.inspect("gate", GRAY, timeout_s=0.2)
            gate.release.set()
            await wait_until(lambda: gate.finished == 1, "the timed-out run finished")
            # The late RESULT arrives around now; it must not answer anything else.
            dark = np.full((48, 64), 10, np.uint8)
            for _ in range(3):
                result = await client.inspect("brightness", dark)
                assert result.inspection == "brightness"
                assert result.data["value"] == 10.0
                assert not result.passed
                assert (await client.request(lambda r: Ping(r, "p"))).data == "p"
            assert client.reconnects == 0

    run(body())


# ----------------------------------------------------------------------------- auth, versions


def test_auth_token() -> None:
    async def body() -> None:
        settings = ServerSettings(port=0, auth_token="s3cret")
        async with (
            VisionServer(builtin_catalog(), settings) as server,
            client_for(server, auth_token="s3cret") as client,
        ):
            assert await client.ping() >= 0.0
            for token in ("wrong", None, ""):
                refused = client_for(server, auth_token=token)
                with pytest.raises(NotAuthenticated) as caught:
                    await refused.connect()
                assert caught.value.fatal
                assert not refused.connected

    run(body())


class FrameStream:
    """The server side of one scripted connection: read frames, write frames."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.decoder = FrameDecoder()

    async def next(self) -> Frame | None:
        while (frame := self.decoder.next_frame()) is None:
            if self.decoder.eof:
                return None
            self.decoder.feed(await self.reader.read(65536))
        return frame

    async def send(self, frame: Frame) -> None:
        self.writer.write(frame.serialize())
        await self.writer.drain()


Script = Callable[[FrameStream], Awaitable[None]]


@contextlib.asynccontextmanager
async def scripted_server(script: Script) -> AsyncIterator[int]:
    """A fake server running ``script`` on each connection; yields its port. On exit it waits
    for the scripts to end (they see the client's end of stream)."""
    handlers: set[asyncio.Task[Any]] = set()

    async def on_connect(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        handlers.add(task)
        try:
            await script(FrameStream(reader, writer))
        finally:
            writer.close()

    server = await asyncio.start_server(on_connect, "127.0.0.1", 0)
    async with server:
        yield server.sockets[0].getsockname()[1]
        if handlers:
            await asyncio.wait(handlers, timeout=5.0)


def _welcome(request_id: int, version: tuple[int, int]) -> Frame:
    return Welcome(request_id, version, "fake", "0").to_frame(version)


def test_hello_offers_the_versions_the_client_speaks() -> None:
    hellos: list[Frame] = []

    async def script(stream: FrameStream) -> None:
        hello = await stream.next()
        assert hello is not None
        hellos.append(hello)
        await stream.send(_welcome(hello.request_id, (1, 0)))
        close = await stream.next()
        assert close is not None
        assert close.type == MessageType.CLOSE
        await stream.send(Close(0, "bye").to_frame((1, 0)))

    async def body() -> None:
        async with scripted_server(script) as port:
            client = VisionClient("127.0.0.1", port, client_name="tester/1")
            welcome = await client.connect()
            assert welcome.version == (1, 0)
            await client.close()

    run(body())
    (hello,) = hellos
    assert hello.type == MessageType.HELLO
    assert hello.version == (1, 1)
    assert hello.request_id != 0
    assert hello.metadata == {
        "versions": [[1, 1]],
        "client": "tester/1",
        # What the client can receive (SPEC §5.1): the server bounds its answers by it.
        "max_frame_bytes": 256 * 1024 * 1024,
    }


@pytest.mark.parametrize("version", [(2, 0), (1, 7)])
def test_a_welcome_of_a_version_the_client_does_not_speak_is_refused(
    version: tuple[int, int],
) -> None:
    async def script(stream: FrameStream) -> None:
        hello = await stream.next()
        assert hello is not None
        await stream.send(_welcome(hello.request_id, version))
        while await stream.next() is not None:
            pass

    async def body() -> None:
        async with scripted_server(script) as port:
            client = VisionClient("127.0.0.1", port, reconnect=ReconnectPolicy(attempts=0))
            with pytest.raises(UnsupportedVersion):
                await client.connect()
            assert not client.connected

    run(body())


def test_unsupported_version_from_the_server_reaches_the_caller() -> None:
    async def script(stream: FrameStream) -> None:
        hello = await stream.next()
        assert hello is not None
        error = Error(
            hello.request_id,
            ErrorCode.UNSUPPORTED_VERSION,
            "I speak 2.x only",
            True,
            {"supported": [[2, 3]]},
        )
        await stream.send(error.to_frame((2, 3)))

    async def body() -> None:
        async with scripted_server(script) as port:
            client = VisionClient("127.0.0.1", port)
            with pytest.raises(UnsupportedVersion) as caught:
                await client.connect()
            assert caught.value.details == {"supported": [[2, 3]]}
            assert caught.value.fatal

    run(body())


def test_requests_crossing_the_servers_close_fail_as_shutting_down() -> None:
    async def script(stream: FrameStream) -> None:
        hello = await stream.next()
        assert hello is not None
        await stream.send(_welcome(hello.request_id, (1, 0)))
        request = await stream.next()
        assert request is not None
        assert request.type == MessageType.INSPECT
        # Stopping: this request "crossed" the CLOSE and is never answered.
        await stream.send(Close(0, "server shutting down").to_frame((1, 0)))

    async def body() -> None:
        async with scripted_server(script) as port:
            client = VisionClient("127.0.0.1", port, reconnect=ReconnectPolicy(attempts=0))
            await client.connect()
            with pytest.raises(ShuttingDown):
                await client.inspect("anything", GRAY)
            assert not client.connected

    run(body())


# ----------------------------------------------------------------------------- connection loss

CRASHING_SERVER = """
import asyncio, sys, threading
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server import Catalog, InspectionOutcome
from vision_server.server import ServerSettings, VisionServer

class Stall:
    name, type, camera, uses_depth, frames = "stall", "presence", "tool", False, 1

    def run(self, image, *, overlay):
        print("started", flush=True)
        threading.Event().wait()  # until the test kills this process

async def main():
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [Stall()])
    server = VisionServer(catalog, ServerSettings(port=0))
    await server.start()
    print(server.port, flush=True)
    await server.serve_forever()

asyncio.run(main())
"""


def test_after_a_server_crash_in_flight_requests_are_lost_and_the_next_one_reconnects() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", CRASHING_SERVER],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        port = int(proc.stdout.readline())

        async def body() -> None:
            assert proc.stdout is not None
            client = VisionClient("127.0.0.1", port, request_timeout_s=10.0)
            await client.connect()
            in_flight = asyncio.create_task(client.inspect("stall", GRAY))
            assert await asyncio.to_thread(proc.stdout.readline) == "started\n"
            proc.kill()
            await asyncio.to_thread(proc.wait)
            with pytest.raises(ConnectionLost):
                await in_flight
            assert not client.connected

            # A new server on the same port: the next request reconnects, the lost one is
            # not sent again.
            counting = Counting()
            async with VisionServer(make_catalog(counting), ServerSettings(port=port)):
                result = await client.inspect("stall", GRAY)
                assert result.data == {"runs": 1}
                assert await client.ping() >= 0.0
                assert counting.runs == 1
                assert client.reconnects == 1
                await client.close()

        run(body())
    finally:
        proc.kill()
        proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def test_connection_lost_when_nothing_listens() -> None:
    holder, port = free_port_nobody_listens_on()

    async def body() -> None:
        client = VisionClient("127.0.0.1", port, reconnect=ReconnectPolicy(attempts=1))
        with pytest.raises(ConnectionLost, match=f"127.0.0.1:{port}"):
            await client.connect()
        with pytest.raises(ConnectionLost):
            await client.ping()  # the first request opens the connection itself
        assert not client.connected
        with pytest.raises(ConnectionLost):
            await wait_for_server("127.0.0.1", port, timeout_s=0.2)

    with holder:
        run(body())


def test_wait_for_server_returns_the_welcome() -> None:
    async def body() -> None:
        async with VisionServer(builtin_catalog(), ServerSettings(port=0)) as server:
            welcome = await wait_for_server("127.0.0.1", server.port, timeout_s=5.0)
            assert welcome.server_name == "cellvision"

    run(body())


def test_graceful_close_answers_what_is_in_flight_first(gate: Gate) -> None:
    async def body() -> None:
        async with VisionServer(make_catalog(gate), ServerSettings(port=0)) as server:
            client = client_for(server)
            await client.connect()
            in_flight = asyncio.create_task(client.inspect("gate", GRAY))
            await wait_until(lambda: gate.entered == 1, "the inspection started")
            closing = asyncio.create_task(client.close())
            sessions = server.tcp.connections  # white-box: wait until the server read our CLOSE
            await wait_until(
                lambda: all(s.conn.state is State.CLOSING for s in sessions) and bool(sessions),
                "the server got CLOSE",
            )
            assert not closing.done()
            gate.release.set()
            assert (await in_flight).data == {"gate": True}
            await closing
            assert not client.connected
            with pytest.raises(ClientClosed):
                await client.ping()

    run(body())


# ----------------------------------------------------------------------------- sync facade


@contextlib.contextmanager
def server_in_thread(catalog: Catalog, **settings: Any) -> Iterator[VisionServer]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="test-server", daemon=True)
    thread.start()
    server = VisionServer(catalog, ServerSettings(port=0, **settings))
    try:
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(10.0)
        yield server
    finally:
        asyncio.run_coroutine_threadsafe(server.stop(), loop).result(30.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()


def _client_threads() -> int:
    return sum(t.name == "vision-client" for t in threading.enumerate())


def test_sync_client() -> None:
    threads_before = _client_threads()
    with (
        server_in_thread(builtin_catalog()) as server,
        SyncVisionClient("127.0.0.1", server.port, request_timeout_s=10.0) as client,
    ):
        assert client.welcome.server_name == "cellvision"
        assert client.ping() >= 0.0
        assert [i["name"] for i in client.list_inspections()] == ["brightness"]
        result = client.inspect("brightness", GRAY, overlay=True)
        assert result.passed
        overlay = overlay_image(result)
        assert overlay is not None
        np.testing.assert_array_equal(overlay, GRAY)
        with pytest.raises(UnknownInspection):
            client.inspect("nope", GRAY)
        assert client.ping() >= 0.0
    assert _client_threads() == threads_before


def test_sync_client_that_cannot_connect_leaves_no_thread() -> None:
    threads_before = _client_threads()
    holder, port = free_port_nobody_listens_on()
    with holder, pytest.raises(ConnectionLost):
        SyncVisionClient("127.0.0.1", port, connect_timeout_s=2.0)
    assert _client_threads() == threads_before


def test_a_peer_that_is_not_a_cellvision_server_is_reported_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """An HTTP port (the web console's) given as the server: connect() fails with the protocol
    error, and nothing else is printed about it (a warning from the read loop showed it twice)."""

    async def http(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read(64)
        writer.write(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
        await writer.drain()
        writer.close()

    async def body() -> None:
        server = await asyncio.start_server(http, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        async with server:
            client = VisionClient("127.0.0.1", port, connect_timeout_s=5.0)
            with pytest.raises(NotCellvision, match="not a cellvision server.*HTTP server"):
                await client.connect()
            await client.close()

    with caplog.at_level("WARNING", logger="robot_client"):
        run(body())
    assert not [r for r in caplog.records if "bad data" in r.getMessage()]
