"""A camera replaced by a reload outlives the requests that use it (issue 13, hole 7).

A real folder camera (files in a temporary directory) served by a real server; a reload that
changes the camera's settings arrives while a grab is held in progress by a gate, so the
request is deterministically running across the reload. Before the fix the reload closed the
old camera at once and the held requests got CAMERA_UNAVAILABLE "the camera is closed".
"""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from loopback import client_for, run, wait_until

from protocol import CellvisionError, DeadlineExceeded, Reload, Reloaded, array_from_payload
from robot_client import VisionClient
from vision_server.cameras import (
    Camera,
    CameraFrame,
    CameraSettings,
    FolderCamera,
    FolderCameraSettings,
)
from vision_server.commands.admin import call
from vision_server.server import ServerSettings, VisionServer
from vision_server.service.runtime import CameraFactory, CellRuntime

CONFIG = """\
server: {{port: 0}}
cameras:
  replay: {{source: folder, path: frames, color: {color}}}
inspections:
  - {{name: replayed, type: presence, camera: replay, measure: mean_intensity, min: 0}}
"""


def write_cell(directory: Path, *, color: str) -> Path:
    """The configuration; the first time also the images (never rewritten while served)."""
    frames = directory / "frames"
    if not frames.is_dir():
        frames.mkdir()
        for i in range(4):
            cv2.imwrite(str(frames / f"f{i}.png"), np.full((24, 32), 40 * (i + 1), np.uint8))
    path = directory / "cell.yaml"
    path.write_text(CONFIG.format(color=color), encoding="utf-8")
    return path


class GrabGate:
    """Holds every grab of the cameras built while ``closed`` until the test opens it."""

    def __init__(self) -> None:
        self.closed = True
        self.opened = threading.Event()
        self._lock = threading.Lock()
        self.entered = 0

    def enter(self) -> None:
        with self._lock:
            self.entered += 1
        assert self.opened.wait(20.0), "the test never opened the gate"


class GatedFolderCamera(FolderCamera):
    def __init__(
        self, name: str, settings: FolderCameraSettings, base_dir: Path, gate: GrabGate | None
    ) -> None:
        super().__init__(name, settings, base_dir=base_dir)
        self.gate = gate

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        if self.gate is not None:
            self.gate.enter()
        return super().grab(timeout_s=timeout_s, newer_than=newer_than)


def gated_factory(gate: GrabGate) -> CameraFactory:
    def factory(name: str, settings: CameraSettings, base_dir: Path) -> Camera:
        assert isinstance(settings, FolderCameraSettings)
        return GatedFolderCamera(name, settings, base_dir, gate if gate.closed else None)

    return factory


def reload_over_the_protocol(server: VisionServer) -> Reloaded:
    answer = call("127.0.0.1", server.port, Reload, timeout_s=10.0)
    assert isinstance(answer, Reloaded)
    return answer


def test_requests_running_across_a_reload_finish_with_the_old_camera(tmp_path: Path) -> None:
    path = write_cell(tmp_path, color="gray")
    gate = GrabGate()
    runtime = CellRuntime(path, camera_factory=gated_factory(gate))

    async def body() -> None:
        settings = ServerSettings(port=0, workers=4)  # two are held by the gate
        server = VisionServer(runtime.catalog, settings, reloader=runtime.reload)
        async with server, client_for(server) as client:
            old = runtime.catalog.cameras["replay"]
            inspecting = asyncio.ensure_future(client.inspect("replayed"))
            capturing = asyncio.ensure_future(client.capture("replay"))
            await wait_until(lambda: gate.entered == 2, "both grabs are held in progress")

            write_cell(tmp_path, color="bgr")  # the camera's settings change
            gate.closed = False  # the new camera is not held
            await asyncio.to_thread(reload_over_the_protocol, server)
            new = runtime.catalog.cameras["replay"]
            assert new is not old
            assert not old.closed, "the old camera is still in use"

            # A request that starts after the reload uses the new camera (BGR frames).
            after = await client.capture("replay")
            assert array_from_payload(after.images[0]).shape == (24, 32, 3)

            gate.opened.set()
            result = await inspecting  # no CAMERA_UNAVAILABLE "the camera is closed"
            frames = await capturing
            assert result.passed
            assert array_from_payload(frames.images[0]).shape == (24, 32), "the old camera's"
            await wait_until(lambda: old.closed, "the old camera is closed after its requests")
            assert not new.closed

    try:
        run(body())
    finally:
        gate.opened.set()
        runtime.close()


def test_a_request_past_its_deadline_keeps_the_camera_until_its_grab_ends(
    tmp_path: Path,
) -> None:
    # The client gets DEADLINE_EXCEEDED while the grab goes on in a worker thread: the
    # worker, not the answered request, holds the old camera from then on.
    path = write_cell(tmp_path, color="gray")
    gate = GrabGate()
    runtime = CellRuntime(path, camera_factory=gated_factory(gate))

    async def body() -> None:
        server = VisionServer(runtime.catalog, ServerSettings(port=0), reloader=runtime.reload)
        async with server, client_for(server) as client:
            old = runtime.catalog.cameras["replay"]
            with pytest.raises(DeadlineExceeded):
                await client.inspect("replayed", deadline_s=0.05)
            await wait_until(lambda: gate.entered == 1, "the grab is held in a worker")
            write_cell(tmp_path, color="bgr")
            gate.closed = False
            await asyncio.to_thread(reload_over_the_protocol, server)
            assert not old.closed, "the worker still grabs from the old camera"
            gate.opened.set()
            await wait_until(lambda: old.closed, "the old camera is closed after the grab")

    try:
        run(body())
    finally:
        gate.opened.set()
        runtime.close()


def test_a_client_hammering_through_reloads_never_sees_a_closed_camera(tmp_path: Path) -> None:
    path = write_cell(tmp_path, color="gray")
    runtime = CellRuntime(path)
    replaced: list[Camera] = []

    async def hammer(client: VisionClient, stop: asyncio.Event, errors: list[str]) -> int:
        answered = 0
        while not stop.is_set():
            try:
                if answered % 2:
                    await client.capture("replay")
                else:
                    await client.inspect("replayed")
            except CellvisionError as exc:
                errors.append(f"{exc.code.name}: {exc.message}")
            answered += 1
        return answered

    async def body() -> None:
        settings = ServerSettings(port=0, workers=4)  # two are held by the gate
        server = VisionServer(runtime.catalog, settings, reloader=runtime.reload)
        async with server, client_for(server) as a, client_for(server) as b:
            stop = asyncio.Event()
            errors: list[str] = []
            async with asyncio.TaskGroup() as group:
                counts = [group.create_task(hammer(c, stop, errors)) for c in (a, b)]
                for k in range(8):
                    replaced.append(runtime.catalog.cameras["replay"])
                    write_cell(tmp_path, color="bgr" if k % 2 == 0 else "gray")
                    await asyncio.to_thread(reload_over_the_protocol, server)
                stop.set()
            assert errors == []
            assert all(c.result() > 0 for c in counts)
            await wait_until(
                lambda: all(camera.closed for camera in replaced), "replaced cameras are closed"
            )
            assert not runtime.catalog.cameras["replay"].closed

    try:
        run(body(), timeout_s=60.0)
    finally:
        runtime.close()


class SlowToClose(FolderCamera):
    """A camera whose close() blocks (a hung driver) until the test lets it go."""

    closing = threading.Event()
    may_close = threading.Event()

    def close(self) -> None:
        if not self.closed:
            SlowToClose.closing.set()
            assert SlowToClose.may_close.wait(20.0), "the test never let the camera close"
        super().close()


def test_reload_does_not_wait_for_a_replaced_camera_to_close(tmp_path: Path) -> None:
    path = write_cell(tmp_path, color="gray")
    SlowToClose.closing.clear()
    SlowToClose.may_close.clear()

    def factory(name: str, settings: CameraSettings, base_dir: Path) -> Camera:
        assert isinstance(settings, FolderCameraSettings)
        return SlowToClose(name, settings, base_dir=base_dir)

    runtime = CellRuntime(path, camera_factory=factory)
    try:
        old = runtime.catalog.cameras["replay"]
        write_cell(tmp_path, color="bgr")
        done = threading.Event()
        reloader = threading.Thread(target=lambda: (runtime.reload(), done.set()))
        reloader.start()
        # Neither reload (it may run on the event loop: SIGHUP) nor the old camera's close
        # waits for the other: the close has started and is blocked, the reload is done.
        assert SlowToClose.closing.wait(20.0), "the unused old camera is being closed"
        assert done.wait(20.0), "reload waited for the old camera to close"
        assert not old.closed
        assert runtime.catalog.cameras["replay"] is not old
    finally:
        SlowToClose.may_close.set()
        runtime.close()  # waits for the closing of the replaced camera
    assert old.closed


def test_the_runtime_closes_what_is_still_leased_when_it_closes(tmp_path: Path) -> None:
    path = write_cell(tmp_path, color="gray")
    runtime = CellRuntime(path)
    lease = runtime.catalog.acquire()
    old = runtime.catalog.cameras["replay"]
    write_cell(tmp_path, color="bgr")
    runtime.reload()
    assert not old.closed  # leased
    runtime.close()
    assert old.closed
    assert runtime.catalog.cameras["replay"].closed
    lease.release()  # after close: nothing left to do, nothing raises
