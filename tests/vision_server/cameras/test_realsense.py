"""The ``realsense`` camera against a fake pyrealsense2 that behaves like the SDK with devices
on a bus (tests/helpers/fake_realsense.py), registered as ``sys.modules["pyrealsense2"]``.

Only what a recording cannot show is tested here: choosing a device by serial among several,
absent devices and modes they do not offer, a late frame, a device busy with another
pipeline, unplugging mid-stream, latest-frame semantics. Colour, aligned depth in mm by the
depth scale, the stream's intrinsics and their distortion model are tested against the real
SDK playing recordings (test_realsense_sdk.py)."""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from fake_realsense import Bus, FakeDevice, fake_pyrealsense2

from protocol import CameraUnavailable
from vision_server.cameras import (
    ManualClock,
    RealSenseCamera,
    RealSenseCameraSettings,
)
from vision_server.cameras.realsense import depth_to_mm


@pytest.fixture
def bus(monkeypatch: pytest.MonkeyPatch) -> Bus:
    module, bus = fake_pyrealsense2(FakeDevice("123456789012"))
    monkeypatch.setitem(sys.modules, "pyrealsense2", module)
    return bus


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


def camera(clock: ManualClock, **settings: object) -> Iterator[RealSenseCamera]:
    cam = RealSenseCamera("rgbd", RealSenseCameraSettings(**settings), clock=clock)  # type: ignore[arg-type]
    cam.open()
    try:
        yield cam
    finally:
        cam.close()


def grab_error(cam: RealSenseCamera) -> str:
    with pytest.raises(CameraUnavailable) as excinfo:
        cam.grab(timeout_s=0.5)
    return excinfo.value.message


def test_depth_scale_conversion_rounds_and_clips() -> None:
    raw = np.array([[0, 1, 15, 70000 % 65536]], np.uint16)
    assert depth_to_mm(raw, 0.001).tolist() == raw.tolist()
    assert depth_to_mm(raw, 0.0001).tolist() == [[0, 0, 2, 446]]
    assert depth_to_mm(np.array([[65535]], np.uint16), 0.01).tolist() == [[65535]]


def test_a_grab_drops_framesets_queued_before_it(bus: Bus, clock: ManualClock) -> None:
    for cam in camera(clock, depth=False):
        first = cam.grab(timeout_s=1.0)
        assert first.color[0, 0, 0] == 1
        bus.queue_stale("123456789012", 3)  # frames 2..4, captured before the next grab
        second = cam.grab(timeout_s=1.0)
        assert second.color[0, 0, 0] == 5
        assert second.index == first.index + 1


def test_the_serial_selects_the_device(monkeypatch: pytest.MonkeyPatch, clock: ManualClock) -> None:
    module, _ = fake_pyrealsense2(FakeDevice("111", tag=1), FakeDevice("222", tag=2))
    monkeypatch.setitem(sys.modules, "pyrealsense2", module)
    for cam in camera(clock, serial="222", depth=False):
        assert cam.grab(timeout_s=1.0).color[0, 0, 1] == 2
    for cam in camera(clock):
        assert "several are (serials: 111, 222); set serial to choose one" in grab_error(cam)
    for cam in camera(clock, serial="333"):
        assert "no RealSense device with serial 333 (connected: 111, 222)" in grab_error(cam)


def test_no_device_and_an_unoffered_mode_are_named(bus: Bus, clock: ManualClock) -> None:
    for cam in camera(clock, width=1920, height=1080):
        message = grab_error(cam)
        assert "camera 'rgbd' (realsense)" in message
        assert "does not offer colour 1920x1080 and depth 1920x1080 at 30 fps" in message
    bus.device("123456789012").plugged = False
    for cam in camera(clock):
        assert "no RealSense device is connected (serials: none)" in grab_error(cam)


def test_a_late_frame_is_a_timeout_and_the_camera_stays_connected(
    bus: Bus, clock: ManualClock
) -> None:
    for cam in camera(clock, depth=False):
        cam.grab(timeout_s=1.0)
        bus.device("123456789012").stalled = True
        assert "no frame from RealSense 123456789012 within 0.5 s" in grab_error(cam)
        assert cam.status()["connected"]
        bus.device("123456789012").stalled = False
        assert cam.grab(timeout_s=1.0).index == 1


def test_a_grab_waits_for_anothers_read_no_longer_than_its_timeout(
    bus: Bus, clock: ManualClock
) -> None:
    device = bus.device("123456789012")
    device.hold = threading.Event()
    for cam in camera(clock, depth=False):
        with ThreadPoolExecutor(1) as pool:
            first = pool.submit(cam.grab, timeout_s=30.0)
            assert device.waiting.wait(30.0), "the first grab reads from the device"
            with pytest.raises(CameraUnavailable, match="busy with another capture for 0.05 s"):
                cam.grab(timeout_s=0.05)
            # Health answers at once, without waiting for the device.
            assert cam.status()["state"] == "up"
            device.hold.set()
            assert first.result(30.0).index == 0


def test_a_device_streaming_for_another_camera_is_busy_until_released(
    bus: Bus, clock: ManualClock
) -> None:
    for old in camera(clock):
        for new in camera(clock, fps=30, depth=False):
            assert "Device or resource busy" in str(new.status()["last_error"])
            old.close()
            assert new.grab(timeout_s=1.0).depth is None


def test_unplugged_mid_stream_then_back_reconnects(bus: Bus, clock: ManualClock) -> None:
    device = bus.device("123456789012")
    for cam in camera(clock, reconnect_interval_s=2.0):
        cam.grab(timeout_s=1.0)
        device.plugged = False
        assert "RealSense device 123456789012 was disconnected" in grab_error(cam)
        assert bus.pipelines == []  # the backend stopped its pipeline
        status = cam.status()
        assert status["state"] == "down"
        assert not status["connected"]
        device.plugged = True
        # Not yet due: refused at once with the cause, without touching the device.
        assert "disconnected; retrying every 2 s" in grab_error(cam)
        clock.advance(2.0)
        frame = cam.grab(timeout_s=1.0)
        assert frame.index == 1
        assert cam.status()["reconnects"] == 1
        assert cam.status()["last_error"] is None


def test_without_pyrealsense2_the_camera_says_which_extra_to_install(
    monkeypatch: pytest.MonkeyPatch, clock: ManualClock
) -> None:
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import raises ImportError
    for cam in camera(clock):
        assert "pip install 'cellvision[realsense]'" in grab_error(cam)
