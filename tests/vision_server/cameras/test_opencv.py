"""The opencv source, for real: video files written by the test, read by cv2.VideoCapture.

Where a verdict is about time (playback pacing, skipped frames, reconnect pauses, a grab that
must not wait), the camera runs on a :class:`ManualClock` that only the test advances; the
other tests wait for conditions, never for a duration.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from protocol import CameraUnavailable
from vision_server.cameras import (
    CameraFrame,
    Intrinsics,
    ManualClock,
    OpenCVCamera,
    OpenCVCameraSettings,
    make_camera,
)
from vision_server.cameras.base import color_image
from vision_server.cameras.opencv import source_kind

from .conftest import HEIGHT, WIDTH, frame_number, write_video

GRAB_TIMEOUT_S = 5.0


FPS = 32.0
"""Playback rate of the paced tests: its period (1/32 s) is exact in binary, so the manual
clock lands exactly on the reader's schedule."""
PERIOD_S = 1.0 / FPS


def wait_for(predicate: Callable[[], bool], what: str = "condition") -> None:
    """Wait for a condition that worker threads bring about (real time only bounds a hang)."""
    deadline = time.monotonic() + 30.0
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not met")
        time.sleep(0.002)


def in_thread(fn: Callable[[], object]) -> tuple[threading.Thread, list[object]]:
    """Run ``fn`` in a thread; its return value or exception lands in the list."""
    out: list[object] = []

    def target() -> None:
        try:
            out.append(fn())
        except BaseException as exc:  # handed to the test
            out.append(exc)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread, out


def next_frame(camera: OpenCVCamera, clock: ManualClock) -> None:
    """Let one playback period pass and wait until the reader has published its frame."""
    wait_for(lambda: clock.waiters >= 1, "the reader waits for its next frame time")
    frames = camera.status()["frames"]
    clock.advance(PERIOD_S)
    wait_for(lambda: camera.status()["frames"] == frames + 1, "the reader published a frame")


@pytest.fixture
def opened() -> Iterator[list[OpenCVCamera]]:
    """Cameras appended here are closed after the test."""
    cameras: list[OpenCVCamera] = []
    yield cameras
    for camera in cameras:
        camera.close()


def open_camera(
    opened: list[OpenCVCamera],
    settings: OpenCVCameraSettings,
    base_dir: Path,
    clock: ManualClock | None = None,
) -> OpenCVCamera:
    camera = make_camera("cam", settings, base_dir=base_dir, clock=clock)
    assert isinstance(camera, OpenCVCamera)
    opened.append(camera)
    camera.open()
    return camera


def test_frames_are_bgr_uint8_with_increasing_indices(
    video: Path, opened: list[OpenCVCamera]
) -> None:
    camera = open_camera(opened, OpenCVCameraSettings(video.name), video.parent)
    first = camera.grab(timeout_s=GRAB_TIMEOUT_S)
    assert first.color.shape == (HEIGHT, WIDTH, 3)
    assert first.color.dtype == np.uint8
    assert first.depth is None
    assert not first.color.flags.writeable
    second = camera.grab(timeout_s=GRAB_TIMEOUT_S)
    assert second.index > first.index
    assert second.timestamp >= first.timestamp
    assert camera.source == "opencv"
    assert not camera.has_depth


def test_a_grab_returns_a_frame_captured_after_the_call(
    video: Path, opened: list[OpenCVCamera]
) -> None:
    clock = ManualClock()
    camera = open_camera(opened, OpenCVCameraSettings(str(video), fps=FPS), video.parent, clock)
    # The file's first frame, on air at once (newer_than=-1: the reader may have published it
    # before this call, and the next one waits for the clock).
    first = camera.grab(timeout_s=GRAB_TIMEOUT_S, newer_than=-1)
    assert abs(frame_number(first.color) - 0) <= 1  # JPEG moves the grey level a little
    for _ in range(15):  # 15 frames go by; none of them may be handed out later
        next_frame(camera, clock)
    called_at = clock.time()
    thread, out = in_thread(lambda: camera.grab(timeout_s=GRAB_TIMEOUT_S))
    wait_for(lambda: clock.waiters == 2, "the grab and the reader both wait")
    clock.advance(PERIOD_S)
    thread.join(30.0)
    fresh = out[0]
    assert isinstance(fresh, CameraFrame)
    assert fresh.index == first.index + 16
    assert fresh.timestamp == pytest.approx(called_at + PERIOD_S)
    # Playback went on while nobody grabbed: the content skipped ahead instead of continuing
    # with the next buffered frame.
    assert abs(frame_number(fresh.color) - 16) <= 1


def test_newer_than_and_grab_many_give_distinct_frames(
    video: Path, opened: list[OpenCVCamera]
) -> None:
    camera = open_camera(opened, OpenCVCameraSettings(str(video)), video.parent)
    frame = camera.grab(timeout_s=GRAB_TIMEOUT_S)
    newer = camera.grab(timeout_s=GRAB_TIMEOUT_S, newer_than=frame.index)
    assert newer.index > frame.index
    frames = camera.grab_many(5, timeout_s=GRAB_TIMEOUT_S)
    indices = [f.index for f in frames]
    assert indices == sorted(set(indices))
    assert len(indices) == 5
    numbers = [frame_number(f.color) for f in frames]
    assert numbers == sorted(numbers)


def test_missing_file_is_unavailable_at_once_then_reconnects_when_it_appears(
    tmp_path: Path, opened: list[OpenCVCamera]
) -> None:
    clock = ManualClock()
    settings = OpenCVCameraSettings("late.avi", reconnect_interval_s=0.25, loop_file=True)
    camera = open_camera(opened, settings, tmp_path, clock)
    wait_for(lambda: camera.status()["state"] == "down", "the camera is down")
    # Down means "raise now with the cause", not "wait out the timeout": the clock stands
    # still, so a grab that waited would never return.
    thread, out = in_thread(lambda: camera.grab(timeout_s=30.0))
    thread.join(30.0)
    assert not thread.is_alive(), "a grab from a down camera waits instead of raising"
    error = out[0]
    assert isinstance(error, CameraUnavailable)
    assert error.message == (
        "camera 'cam' (opencv): video file late.avi does not exist; retrying every 0.25 s"
    )
    assert error.details["camera"] == "cam"
    status = camera.status()
    assert status["connected"] is False
    assert "does not exist" in status["last_error"]

    write_video(tmp_path / "late.avi", 30)
    assert camera.status()["state"] == "down", "no retry before the reconnect interval"
    wait_for(lambda: clock.waiters == 1, "the reader pauses before retrying")
    clock.advance(0.25)
    wait_for(lambda: camera.status()["state"] == "up", "the camera reconnected by itself")
    frame = camera.grab(timeout_s=GRAB_TIMEOUT_S, newer_than=-1)
    assert frame.color.shape == (HEIGHT, WIDTH, 3)
    status = camera.status()
    assert status["connected"] is True
    assert status["reconnects"] == 1


def test_requested_resolution_is_delivered(video: Path, opened: list[OpenCVCamera]) -> None:
    both = open_camera(opened, OpenCVCameraSettings(str(video), width=80, height=60), video.parent)
    assert both.grab(timeout_s=GRAB_TIMEOUT_S).color.shape == (60, 80, 3)
    status = both.status()
    assert (status["width"], status["height"]) == (80, 60)
    assert (status["native_width"], status["native_height"]) == (WIDTH, HEIGHT)
    # One of the two keeps the aspect ratio.
    width_only = open_camera(opened, OpenCVCameraSettings(str(video), width=320), video.parent)
    assert width_only.grab(timeout_s=GRAB_TIMEOUT_S).color.shape == (240, 320, 3)


def test_frames_that_do_not_fit_the_intrinsics_are_refused(
    video: Path, opened: list[OpenCVCamera]
) -> None:
    intrinsics = Intrinsics(320, 240, 300.0, 300.0, 159.5, 119.5)
    camera = open_camera(
        opened, OpenCVCameraSettings(str(video), intrinsics=intrinsics), video.parent
    )
    wait_for(lambda: camera.status()["state"] == "down")
    with pytest.raises(CameraUnavailable, match="160x120 but the intrinsics are for 320x240"):
        camera.grab(timeout_s=GRAB_TIMEOUT_S)
    scaled = open_camera(
        opened,
        OpenCVCameraSettings(str(video), width=320, height=240, intrinsics=intrinsics),
        video.parent,
    )
    assert scaled.grab(timeout_s=GRAB_TIMEOUT_S).color.shape == (240, 320, 3)


def test_file_plays_at_fps_setting_and_ends_without_loop(
    tmp_path: Path, opened: list[OpenCVCamera]
) -> None:
    path = write_video(tmp_path / "short.avi", 10, fps=10.0)
    clock = ManualClock()
    camera = open_camera(opened, OpenCVCameraSettings(str(path), fps=FPS), tmp_path, clock)
    camera.grab(timeout_s=GRAB_TIMEOUT_S, newer_than=-1)
    assert camera.status()["playback_fps"] == FPS
    for played in range(1, 10):  # one frame per period of the configured rate, not the file's
        assert camera.status()["frames"] == played
        next_frame(camera, clock)
    wait_for(lambda: clock.waiters == 1, "the reader waits to read past the end")
    clock.advance(PERIOD_S)
    wait_for(lambda: camera.status()["state"] == "ended", "the file ended")
    with pytest.raises(CameraUnavailable, match="ended after 10 frames"):
        camera.grab(timeout_s=GRAB_TIMEOUT_S)
    assert camera.status()["frames"] == 10


def test_looping_file_gives_more_frames_than_it_holds(
    tmp_path: Path, opened: list[OpenCVCamera]
) -> None:
    path = write_video(tmp_path / "loop.avi", 5, fps=60.0)
    camera = open_camera(opened, OpenCVCameraSettings(str(path), loop_file=True), tmp_path)
    frames = camera.grab_many(12, timeout_s=10.0)
    assert len({f.index for f in frames}) == 12
    assert camera.status()["reconnects"] == 0


def test_corrupt_file_is_unavailable(tmp_path: Path, opened: list[OpenCVCamera]) -> None:
    (tmp_path / "bad.avi").write_bytes(b"not a video at all" * 100)
    camera = open_camera(opened, OpenCVCameraSettings("bad.avi"), tmp_path)
    wait_for(lambda: camera.status()["state"] == "down")
    with pytest.raises(CameraUnavailable, match="cannot open video file"):
        camera.grab(timeout_s=GRAB_TIMEOUT_S)


def test_concurrent_grabs_from_several_threads(video: Path, opened: list[OpenCVCamera]) -> None:
    camera = open_camera(opened, OpenCVCameraSettings(str(video)), video.parent)
    results: dict[int, list[int]] = {}
    errors: list[BaseException] = []

    def worker(k: int) -> None:
        try:
            results[k] = [camera.grab(timeout_s=GRAB_TIMEOUT_S).index for _ in range(4)]
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    for indices in results.values():
        assert indices == sorted(set(indices))


def test_close_joins_the_reader_and_is_idempotent(video: Path) -> None:
    camera = make_camera("cam", OpenCVCameraSettings(str(video)), base_dir=video.parent)
    assert isinstance(camera, OpenCVCamera)
    with pytest.raises(CameraUnavailable, match="not opened"):
        camera.grab(timeout_s=0.1)
    with camera:
        camera.grab(timeout_s=GRAB_TIMEOUT_S)
        thread = camera._thread
    assert thread is not None
    assert not thread.is_alive()
    camera.close()
    assert camera.status()["state"] == "closed"
    with pytest.raises(CameraUnavailable, match="closed"):
        camera.grab(timeout_s=0.1)


def test_close_wakes_a_waiting_grab(tmp_path: Path) -> None:
    path = write_video(tmp_path / "slow.avi", 3, fps=1.0)
    clock = ManualClock()
    camera = make_camera("cam", OpenCVCameraSettings(str(path)), base_dir=tmp_path, clock=clock)
    camera.open()
    camera.grab(timeout_s=GRAB_TIMEOUT_S, newer_than=-1)
    thread, out = in_thread(lambda: camera.grab(timeout_s=30.0))
    # The clock stands still: only close() can end this grab.
    wait_for(lambda: clock.waiters == 2, "the grab and the reader both wait")
    camera.close()
    thread.join(30.0)
    assert not thread.is_alive()
    assert len(out) == 1
    assert isinstance(out[0], CameraUnavailable)
    assert "closed" in out[0].message


@pytest.mark.parametrize(
    ("device", "backend", "kind"),
    [
        (0, None, "index"),
        ("/dev/video2", None, "device"),
        ("rtsp://10.0.0.5/stream", None, "url"),
        ("http://cam.local/mjpg", "ffmpeg", "url"),
        ("v4l2src ! videoconvert ! appsink", "gstreamer", "pipeline"),
        ("videos/clip.avi", None, "file"),
    ],
)
def test_source_kind(device: int | str, backend: str | None, kind: str) -> None:
    assert source_kind(device, backend) == kind


def test_stream_credentials_never_appear_in_messages() -> None:
    settings = OpenCVCameraSettings("rtsp://admin:hunter2@10.0.0.5:554/main")
    camera = OpenCVCamera("door", settings)
    described = camera.describe_source()
    assert "hunter2" not in described
    assert "admin:***@10.0.0.5:554" in described
    assert "hunter2" not in str(camera.status())


def test_relative_file_resolves_against_base_dir(tmp_path: Path) -> None:
    camera = make_camera("cam", OpenCVCameraSettings("sub/clip.avi"), base_dir=tmp_path)
    assert isinstance(camera, OpenCVCamera)
    assert camera.target == str(tmp_path / "sub" / "clip.avi")


@pytest.mark.parametrize(
    ("device", "shown"),
    [("sub/clip.avi", "video file sub/clip.avi"), ("{abs}/clips/clip.avi", "video file clip.avi")],
)
def test_clients_see_a_file_as_configured_and_the_log_its_full_path(
    tmp_path: Path, device: str, shown: str, caplog: pytest.LogCaptureFixture
) -> None:
    clock = ManualClock()
    settings = OpenCVCameraSettings(device.format(abs=tmp_path), reconnect_interval_s=60.0)
    camera = make_camera("cam", settings, base_dir=tmp_path, clock=clock)
    with camera:
        wait_for(lambda: camera.status()["state"] == "down", "the camera is down")
        with (
            caplog.at_level("WARNING", logger="vision_server.cameras"),
            pytest.raises(CameraUnavailable) as excinfo,
        ):
            camera.grab(timeout_s=1.0)
    assert f"{shown} does not exist" in excinfo.value.message
    assert str(tmp_path) not in excinfo.value.message
    assert str(tmp_path) in caplog.text


def test_color_image_normalises_channels() -> None:
    bgra = np.zeros((4, 5, 4), np.uint8)
    bgra[..., 2] = 200
    bgr = color_image(bgra)
    assert bgr.shape == (4, 5, 3)
    assert (bgr[..., 2] == 200).all()
    assert color_image(np.zeros((4, 5, 1), np.uint8)).shape == (4, 5)
    with pytest.raises(ValueError, match="8-bit"):
        color_image(np.zeros((4, 5), np.uint16))
    with pytest.raises(ValueError, match="shape"):
        color_image(np.zeros((4, 5, 2), np.uint8))
