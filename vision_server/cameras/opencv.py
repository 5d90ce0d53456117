"""The ``opencv`` source: a device, stream or video file read through ``cv2.VideoCapture``.

A reader thread reads continuously and keeps only the newest frame, so the driver's buffer
never holds stale frames and a grab never returns one: ``grab`` waits for a frame that arrives
after the call started (latest-frame semantics, as a smart camera's trigger would).

When the source is absent or a read fails, the camera is *down*: grabs raise
``CameraUnavailable`` at once with the cause, and the reader retries opening it every
``reconnect_interval_s`` until it delivers frames again (each recovery counts as a reconnect).

Video files play in real time at their nominal frame rate (``fps`` in the settings overrides
it; 30 fps when the file gives none), so that a file behaves like a live camera: a grab gets
the frame "on air" at that moment, and frames that nobody grabbed are skipped, as with a
camera. At the end the file starts again when ``loop_file`` is set; otherwise the camera
*ends*: grabs raise ``CameraUnavailable`` ("ended after N frames") and it is not reopened.

Time comes from the camera's clock (:mod:`vision_server.cameras.clock`): playback pacing, grab
timeouts, stall detection, reconnect pauses and frame timestamps, so that a test can drive
them with a manual clock. A video file is named to clients as configured (see
:func:`vision_server.cameras.base.public_path`); the log gets its full path.
"""

from __future__ import annotations

import logging
import sys
import threading
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit, urlunsplit

import cv2
import numpy as np
from numpy.typing import NDArray

from .base import Camera, CameraFrame, color_image, public_path
from .clock import Clock
from .settings import OpenCVCameraSettings

__all__ = ["OpenCVCamera", "SourceKind", "source_kind"]

log = logging.getLogger("vision_server.cameras")

SourceKind = Literal["index", "device", "url", "pipeline", "file"]

_APIS = {
    "any": cv2.CAP_ANY,
    "v4l2": cv2.CAP_V4L2,
    "ffmpeg": cv2.CAP_FFMPEG,
    "gstreamer": cv2.CAP_GSTREAMER,
}
DEFAULT_FILE_FPS = 30.0
"""Playback rate of a video file that states no usable frame rate."""
_MAX_FILE_FPS = 1000.0

_State = Literal["idle", "connecting", "up", "down", "ended", "closed"]
_Outcome = Literal["failed", "failed_at_once", "loop", "ended", "stopped"]


def source_kind(device: int | str, backend: str | None = None) -> SourceKind:
    """What ``device`` names: a device index, a device path, a stream URL, a GStreamer
    pipeline or a video file."""
    if isinstance(device, int):
        return "index"
    if "://" in device:
        return "url"
    if backend == "gstreamer" and "!" in device:
        return "pipeline"
    if device.startswith("/dev/"):
        return "device"
    return "file"


def _redact(url: str) -> str:
    """``url`` without a password (messages and status go to clients and logs)."""
    try:
        parts = urlsplit(url)
    except ValueError:
        return "<unparsable URL>"
    if parts.password is None:
        return url
    host = parts.hostname or ""
    if parts.port is not None:
        host = f"{host}:{parts.port}"
    netloc = f"{parts.username}:***@{host}" if parts.username else f"***@{host}"
    return urlunsplit(parts._replace(netloc=netloc))


class OpenCVCamera(Camera):
    """A camera read through ``cv2.VideoCapture`` by a background thread. See the module."""

    source = "opencv"

    def __init__(
        self,
        name: str,
        settings: OpenCVCameraSettings,
        *,
        base_dir: Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(name, intrinsics=settings.intrinsics, has_depth=False, clock=clock)
        self.settings = settings
        self.kind: SourceKind = source_kind(settings.device, settings.backend)
        self._target: int | str = settings.device
        if self.kind == "file":
            path = Path(str(settings.device)).expanduser()
            if not path.is_absolute() and base_dir is not None:
                path = base_dir / path
            self._target = str(path)
            self.hide_path(path, public_path(str(settings.device)))
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._state: _State = "idle"
        self._latest: CameraFrame | None = None
        self._last_frame_at: float | None = None  # clock.monotonic() of the newest frame
        self._next_index = 0
        self._frames = 0
        self._reconnects = 0
        self._failed = False
        self._error: str | None = None
        self._native_size: tuple[int, int] | None = None
        self._file_fps: float | None = None
        self._backend_name: str | None = None

    @property
    def target(self) -> int | str:
        """What is handed to ``cv2.VideoCapture`` (a file path is absolute)."""
        return self._target

    def describe_source(self) -> str:
        """The source for messages and the log, without credentials (a file's full path:
        :meth:`unavailable` shows it to clients as configured)."""
        if self.kind == "index":
            return f"device index {self._target}"
        if self.kind == "url":
            return f"stream {_redact(str(self._target))}"
        if self.kind == "pipeline":
            return "GStreamer pipeline"
        if self.kind == "device":
            return f"device {self._target}"
        return f"video file {self._target}"

    # -- lifecycle -------------------------------------------------------------------------

    def open(self) -> None:
        if self.closed:
            raise RuntimeError(f"camera {self.name!r} is closed and cannot be reopened")
        with self._cond:
            if self._thread is not None:
                return
            self._state = "connecting"
            self._thread = threading.Thread(
                target=self._run, name=f"camera-{self.name}", daemon=True
            )
        self._thread.start()

    def close(self) -> None:
        if self.closed:
            return
        super().close()
        self._stop.set()
        with self._cond:
            self._state = "closed"
            self._cond.notify_all()
        thread = self._thread
        if thread is not None:
            # A backend can block in read() for up to its own timeout; do not hang forever.
            thread.join(timeout=self.settings.read_timeout_s + 5.0)
            if thread.is_alive():
                log.warning("camera %r: reader thread still blocked in the backend", self.name)

    # -- grabbing --------------------------------------------------------------------------

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        self._check_open()
        deadline = self._clock.monotonic() + max(timeout_s, 0.0)
        with self._cond:
            if self._thread is None:
                raise self.unavailable("not opened")
            latest = self._latest
            if newer_than is not None:
                threshold = newer_than
            else:
                threshold = latest.index if latest is not None else -1
            while True:
                latest = self._latest
                if latest is not None and latest.index > threshold:
                    return latest
                if self._state == "down":
                    raise self.unavailable(
                        f"{self._error}; retrying every {self.settings.reconnect_interval_s:g} s"
                    )
                if self._state == "ended":
                    raise self.unavailable(str(self._error))
                if self._state == "closed":
                    raise self.unavailable("the camera is closed")
                now = self._clock.monotonic()
                if now >= deadline:
                    raise self.unavailable(self._timeout_cause(timeout_s))
                wake_at = deadline
                stall_at = self._stall_deadline()
                if stall_at is not None:
                    if now >= stall_at:
                        silent_s = now - stall_at + self.settings.read_timeout_s
                        raise self.unavailable(
                            f"no frame from {self.describe_source()} for {silent_s:.1f} s: "
                            f"the source stalled"
                        )
                    wake_at = min(wake_at, stall_at)
                self._clock.wait_until(self._cond, wake_at)

    def _stall_deadline(self) -> float | None:
        """When a live source that is up counts as stalled (monotonic time), else None.

        A driver can block in read() without failing; waiting out every grab's timeout would
        hide that. Files are paced by us and never stall.
        """
        if self._state != "up" or self.kind == "file" or self._last_frame_at is None:
            return None
        return self._last_frame_at + self.settings.read_timeout_s

    def _timeout_cause(self, timeout_s: float) -> str:
        cause = f"no new frame from {self.describe_source()} within {timeout_s:.3g} s"
        if self._state == "connecting":
            return f"{cause} (still connecting)"
        if self._latest is not None:
            age = self._clock.time() - self._latest.timestamp
            cause = f"{cause} (last frame {age:.1f} s ago)"
        return cause

    def status(self) -> dict[str, Any]:
        with self._cond:
            latest = self._latest
            out: dict[str, Any] = {
                "name": self.name,
                "source": self.source,
                "device": self.describe_source(),
                "state": self._state,
                "connected": self._state == "up",
                "frames": self._frames,
                "last_error": self._error,
                "reconnects": self._reconnects,
                "backend": self._backend_name,
            }
            if latest is not None:
                age = self._clock.time() - latest.timestamp
                out["width"], out["height"] = latest.width, latest.height
                out["last_frame_age_s"] = round(age, 3)
                stall_at = self._stall_deadline()
                out["stalled"] = stall_at is not None and self._clock.monotonic() >= stall_at
            if self._native_size is not None:
                out["native_width"], out["native_height"] = self._native_size
            if self._file_fps is not None:
                out["playback_fps"] = self._file_fps
            return out

    # -- reader thread ---------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._read_until_finished()
                return
            except Exception as exc:  # a bug must not kill the reader and leave it "up"
                log.exception("camera %r: reader failed", self.name)
                self._mark_down(f"internal error in the reader: {exc!r}")
                if self._pause(self.settings.reconnect_interval_s):
                    return

    def _read_until_finished(self) -> None:
        """Open, read, reopen after failures, until the file ends or the camera closes."""
        while not self._stop.is_set():
            cap, error = self._open_capture()
            if cap is None:
                self._mark_down(error or "cannot open")
                if self._pause(self.settings.reconnect_interval_s):
                    break
                continue
            try:
                outcome = self._pump(cap)
            finally:
                cap.release()
            if outcome in ("ended", "stopped"):
                break
            # A source that opens but fails before its first frame would otherwise spin.
            if outcome == "failed_at_once" and self._pause(self.settings.reconnect_interval_s):
                break

    def _pause(self, seconds: float) -> bool:
        """Wait ``seconds`` on the camera's clock; True when close() came first."""
        return self._pause_until(self._clock.monotonic() + seconds)

    def _pause_until(self, deadline: float) -> bool:
        """Wait until ``deadline`` (clock.monotonic()); True when close() came first."""
        with self._cond:
            while not self._stop.is_set() and self._clock.monotonic() < deadline:
                self._clock.wait_until(self._cond, deadline)
            return self._stop.is_set()

    def _open_capture(self) -> tuple[cv2.VideoCapture | None, str | None]:
        what = self.describe_source()
        if self.kind in ("file", "device") and "%" not in str(self._target):
            path = Path(str(self._target))
            if not path.exists():
                return None, f"{what} does not exist"
            if self.kind == "file" and not path.is_file():
                return None, f"{what} is not a regular file"
        backend = self.settings.backend or "any"
        if self.kind == "index" and sys.platform == "linux" and backend in ("any", "v4l2"):
            # Saves OpenCV's warnings on every retry, and says which node is missing.
            node = Path(f"/dev/video{self._target}")
            if not node.exists():
                return None, f"{what} does not exist ({node} not found)"
        api = _APIS[backend]
        params: list[int] = []
        if self.kind == "url":
            timeout_ms = int(self.settings.read_timeout_s * 1000)
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms]
            params += [cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms]
        try:
            cap = cv2.VideoCapture(self._target, api, params)
        except cv2.error as exc:
            return None, f"cv2.VideoCapture({what}) failed: {exc}"
        if not cap.isOpened():
            cap.release()
            return None, f"cannot open {what} (backend {backend})"
        try:
            self._backend_name = cap.getBackendName()
        except cv2.error:
            self._backend_name = None
        if self.kind == "file":
            self._file_fps = self._playback_fps(cap)
        else:
            self._configure(cap)
        return cap, None

    def _playback_fps(self, cap: cv2.VideoCapture) -> float:
        if self.settings.fps is not None:
            return self.settings.fps
        nominal = float(cap.get(cv2.CAP_PROP_FPS))
        if not np.isfinite(nominal) or not 0 < nominal <= _MAX_FILE_FPS:
            return DEFAULT_FILE_FPS
        return nominal

    def _configure(self, cap: cv2.VideoCapture) -> None:
        """Ask the device for the configured format; backends ignore what they cannot do."""
        s = self.settings
        props: list[tuple[int, float]] = []
        if s.fourcc is not None:
            props.append((cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*s.fourcc))))
        if s.width is not None:
            props.append((cv2.CAP_PROP_FRAME_WIDTH, float(s.width)))
        if s.height is not None:
            props.append((cv2.CAP_PROP_FRAME_HEIGHT, float(s.height)))
        if s.fps is not None:
            props.append((cv2.CAP_PROP_FPS, s.fps))
        props.append((cv2.CAP_PROP_BUFFERSIZE, 1.0))
        for prop, value in props:
            try:
                cap.set(prop, value)
            except cv2.error as exc:
                log.debug("camera %r: cannot set property %d: %s", self.name, prop, exc)

    def _pump(self, cap: cv2.VideoCapture) -> _Outcome:
        """Read frames until a failure, the end of a file, or close()."""
        period = 1.0 / self._file_fps if self.kind == "file" and self._file_fps else 0.0
        next_due = self._clock.monotonic()
        delivered = 0
        while not self._stop.is_set():
            if period:
                now = self._clock.monotonic()
                if next_due > now:
                    if self._pause_until(next_due):
                        return "stopped"
                elif now - next_due > period:
                    next_due = now  # decoding fell behind: do not rush to catch up
                next_due += period
            try:
                ok, image = cap.read()
            except cv2.error as exc:
                ok, image = False, None
                log.debug("camera %r: read raised %s", self.name, exc)
            if not ok or image is None:
                if self.kind == "file" and delivered > 0:
                    if self.settings.loop_file:
                        return "loop"
                    self._mark_ended(f"{self.describe_source()} ended after {delivered} frames")
                    return "ended"
                self._mark_down(f"reading from {self.describe_source()} failed")
                return "failed" if delivered else "failed_at_once"
            try:
                color = self._convert(image)
            except ValueError as exc:
                self._mark_down(f"{self.describe_source()} gave an unusable frame: {exc}")
                return "failed" if delivered else "failed_at_once"
            self._publish(color, self._clock.time())
            delivered += 1
        return "stopped"

    def _convert(self, image: NDArray[Any]) -> NDArray[np.uint8]:
        color = color_image(image)
        height, width = color.shape[:2]
        self._native_size = (width, height)
        size = self._output_size(width, height)
        if size is not None:
            shrink = size[0] * size[1] < width * height
            interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
            color = np.asarray(cv2.resize(color, size, interpolation=interpolation), np.uint8)
        k = self.intrinsics
        if k is not None and (color.shape[1], color.shape[0]) != (k.width, k.height):
            # Measuring with intrinsics of another resolution would be silently wrong.
            raise ValueError(
                f"frames are {color.shape[1]}x{color.shape[0]} but the intrinsics are for "
                f"{k.width}x{k.height} (set width/height or fix the intrinsics)"
            )
        return color

    def _output_size(self, width: int, height: int) -> tuple[int, int] | None:
        """The configured size for a native ``width`` x ``height`` frame, None if equal."""
        want_w, want_h = self.settings.width, self.settings.height
        if want_w is None and want_h is None:
            return None
        if want_w is None:
            want_w = max(1, round(width * want_h / height))  # type: ignore[operator]
        if want_h is None:
            want_h = max(1, round(height * want_w / width))
        if (want_w, want_h) == (width, height):
            return None
        return want_w, want_h

    def _publish(self, color: NDArray[np.uint8], timestamp: float) -> None:
        with self._cond:
            if self._stop.is_set():
                return
            if self._state != "up":
                if self._failed:
                    self._reconnects += 1
                    self._failed = False
                    log.info("camera %r: %s is back", self.name, self.describe_source())
                self._state = "up"
            self._latest = CameraFrame(color, None, timestamp, self._next_index)
            self._last_frame_at = self._clock.monotonic()
            self._next_index += 1
            self._frames += 1
            self._cond.notify_all()

    def _mark_down(self, error: str) -> None:
        with self._cond:
            if self._stop.is_set():
                return
            if self._state != "down" or error != self._error:
                log.warning("camera %r is unavailable: %s", self.name, error)
            self._state = "down"
            self._error = error
            self._failed = True
            self._cond.notify_all()

    def _mark_ended(self, message: str) -> None:
        with self._cond:
            if self._stop.is_set():
                return
            log.info("camera %r: %s", self.name, message)
            self._state = "ended"
            self._error = message
            self._cond.notify_all()
