"""The opencv source against a scripted live device: unplugging, stalling, device settings.

Video files cannot fail in the middle or hang; a live camera can. ``cv2.VideoCapture`` is
replaced by :class:`FakeCapture`, driven by a :class:`FakeDevice` the test controls; everything
else (reader thread, reconnects, stall detection, conversion) is the real code. The camera runs
on a :class:`ManualClock`: reconnect pauses and stall detection move only when the test advances
it, so no verdict depends on how fast the machine is.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import cv2
import numpy as np
import pytest

from protocol import CameraUnavailable
from vision_server.cameras import CameraFrame, ManualClock, OpenCVCamera, OpenCVCameraSettings

URL = "rtsp://viewer:secret@192.0.2.1/stream"


class FakeDevice:
    """A camera on the network: present or not, delivering frames or hanging in read()."""

    def __init__(self) -> None:
        self.present = True
        self.hang = threading.Event()
        self.hanging = threading.Event()
        """Set while a read() hangs."""
        self.opens = 0
        self.props: dict[int, float] = {}
        self.frames = 0


class FakeCapture:
    device: FakeDevice

    def __init__(self, target: object, api: int = 0, params: object = ()) -> None:
        self.device.opens += 1
        self._open = self.device.present

    def isOpened(self) -> bool:
        return self._open

    def getBackendName(self) -> str:
        return "FAKE"

    def set(self, prop: int, value: float) -> bool:
        self.device.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return self.device.props.get(prop, 0.0)

    def read(self) -> tuple[bool, Any]:
        time.sleep(0.005)  # a device's frame interval, in real time (no verdict depends on it)
        while self.device.hang.is_set():
            self.device.hanging.set()
            time.sleep(0.005)
        self.device.hanging.clear()
        if not self._open or not self.device.present:
            return False, None
        self.device.frames += 1
        image = np.zeros((30, 40, 4), np.uint8)  # BGRA, as some drivers deliver
        image[..., 1] = 100
        return True, image

    def release(self) -> None:
        self._open = False


@pytest.fixture
def device(monkeypatch: pytest.MonkeyPatch) -> FakeDevice:
    fake = FakeDevice()
    monkeypatch.setattr(FakeCapture, "device", fake, raising=False)
    monkeypatch.setattr(cv2, "VideoCapture", FakeCapture)
    return fake


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def camera(device: FakeDevice, clock: ManualClock) -> Iterator[OpenCVCamera]:
    settings = OpenCVCameraSettings(
        URL,
        width=40,
        height=30,
        fps=25,
        fourcc="MJPG",
        reconnect_interval_s=0.05,
        read_timeout_s=0.5,
    )
    cam = OpenCVCamera("door", settings, clock=clock)
    cam.open()
    yield cam
    device.hang.clear()
    cam.close()


def wait_for(predicate: Callable[[], bool], what: str) -> None:
    """Wait for a condition the reader brings about (real time only bounds a hang)."""
    deadline = time.monotonic() + 30.0
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not met")
        time.sleep(0.002)


def reader_paused(device: FakeDevice, clock: ManualClock) -> int:
    """Wait until the reader pauses before reopening; how often it opened the device so far."""
    wait_for(lambda: clock.waiters >= 1, "the reader pauses before reopening")
    return device.opens


def after_pause(camera: OpenCVCamera, clock: ManualClock) -> None:
    """Let the reader's reconnect pause pass, once it is waiting in it."""
    wait_for(lambda: clock.waiters >= 1, "the reader pauses before reopening")
    clock.advance(camera.settings.reconnect_interval_s)


def eventually(fn: Callable[[], CameraFrame]) -> CameraFrame:
    deadline = time.monotonic() + 30.0
    while True:
        try:
            return fn()
        except CameraUnavailable:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.002)


def first_failure(camera: OpenCVCamera, *, timeout_s: float) -> CameraUnavailable:
    """Grab until a grab fails (a frame may still be in flight when the device goes)."""
    for _ in range(1000):
        try:
            camera.grab(timeout_s=timeout_s)
        except CameraUnavailable as exc:
            return exc
    raise AssertionError("the camera kept delivering frames")


def test_device_settings_are_requested_and_frames_converted(
    camera: OpenCVCamera, device: FakeDevice
) -> None:
    frame = camera.grab(timeout_s=5.0)
    assert frame.color.shape == (30, 40, 3)
    assert int(frame.color[0, 0, 1]) == 100
    assert device.props[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert device.props[cv2.CAP_PROP_FRAME_WIDTH] == 40
    assert device.props[cv2.CAP_PROP_FRAME_HEIGHT] == 30
    assert device.props[cv2.CAP_PROP_FPS] == 25
    assert device.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter.fourcc(*"MJPG")
    assert camera.status()["backend"] == "FAKE"


def test_unplugged_device_fails_fast_and_comes_back(
    camera: OpenCVCamera, device: FakeDevice, clock: ManualClock
) -> None:
    before = camera.grab(timeout_s=5.0)
    device.present = False
    message = first_failure(camera, timeout_s=5.0).message
    assert "'door'" in message
    assert "secret" not in message
    assert "retrying every 0.05 s" in message
    for _ in range(3):  # the reader keeps trying to reopen the device, once per interval
        opens = reader_paused(device, clock)
        clock.advance(camera.settings.reconnect_interval_s)
        wait_for(lambda n=opens: device.opens == n + 1, "the reader reopened the device")
    assert camera.status()["connected"] is False

    device.present = True
    after_pause(camera, clock)
    after = eventually(lambda: camera.grab(timeout_s=5.0))
    assert after.index > before.index
    status = camera.status()
    assert status["connected"] is True
    assert status["reconnects"] == 1


def test_a_hanging_driver_is_reported_as_stalled(
    camera: OpenCVCamera, device: FakeDevice, clock: ManualClock
) -> None:
    camera.grab(timeout_s=5.0)
    device.hang.set()
    wait_for(device.hanging.is_set, "the driver hangs in read()")
    assert camera.status()["stalled"] is False
    caught: list[CameraUnavailable] = []

    def grab() -> None:
        try:
            camera.grab(timeout_s=30.0)
        except CameraUnavailable as exc:
            caught.append(exc)

    waiter = threading.Thread(target=grab)
    waiter.start()
    wait_for(lambda: clock.waiters == 1, "the grab waits for a frame")
    clock.advance(camera.settings.read_timeout_s)  # read_timeout_s without a frame: stalled
    waiter.join(30.0)
    assert len(caught) == 1
    assert "stalled" in caught[0].message
    assert camera.status()["stalled"] is True
    device.hang.clear()
    frame = eventually(lambda: camera.grab(timeout_s=5.0))
    assert frame.color.shape == (30, 40, 3)
    assert camera.status()["stalled"] is False


def test_a_bug_in_the_reader_marks_the_camera_down_and_it_recovers(
    camera: OpenCVCamera, device: FakeDevice, clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    camera.grab(timeout_s=5.0)
    original = camera._convert
    broken = threading.Event()
    broken.set()

    def convert(image: Any) -> Any:
        if broken.is_set():
            raise RuntimeError("boom")
        return original(image)

    monkeypatch.setattr(camera, "_convert", convert)
    assert "internal error in the reader" in first_failure(camera, timeout_s=5.0).message
    broken.clear()
    after_pause(camera, clock)
    frame = eventually(lambda: camera.grab(timeout_s=5.0))
    assert frame.color.shape == (30, 40, 3)
    assert camera.status()["reconnects"] >= 1
