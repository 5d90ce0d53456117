"""What the SDK-driven device cameras (``realsense``, ``genicam``) share: the optional SDK
import, a connect/read/disconnect life cycle driven by grabs, and reconnects.

A device camera reads on demand, in the grabbing thread: there is no reader thread, because
both SDKs already buffer frames in their own threads. Grabs are serialised by a lock (one SDK
handle, one reader at a time). ``open()`` connects (a failure marks the camera down, it does
not raise); a grab that finds the device lost disconnects it and the camera is *down*:
grabs raise ``CameraUnavailable`` at once with the cause until ``reconnect_interval_s`` has
passed on the camera's clock, and then the next grab tries again (each recovery counts as a
reconnect). So a device that disappears and comes back
needs no server restart, and a test drives the pacing with a manual clock, not with sleeps.

Subclasses implement :meth:`DeviceCamera._connect`, :meth:`DeviceCamera._read` and
:meth:`DeviceCamera._disconnect`, raising :class:`DeviceError` (the device cannot be used:
down) or :class:`FrameTimeout` (no frame in time: not down, the next grab tries again).
"""

from __future__ import annotations

import importlib
import threading
from abc import abstractmethod
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocol import CameraUnavailable

from .base import Camera, CameraFrame, log
from .clock import Clock
from .settings import Intrinsics

__all__ = ["DeviceCamera", "DeviceError", "FrameTimeout", "import_sdk"]


class DeviceError(Exception):
    """The device cannot deliver frames (absent, refused a setting, lost): the camera is down.

    The message is the cause a client reads (after ``camera 'NAME' (source):``).
    """


class FrameTimeout(Exception):
    """The device is there but gave no frame within the grab's timeout."""


def import_sdk(module: str, *, extra: str) -> ModuleType:
    """Import the vendor SDK ``module`` when the camera first connects.

    Imported then, not when the server starts, so that a configuration naming such a camera
    loads (and other cameras work) on a machine without the SDK, and so that tests can put a
    fake module in ``sys.modules``. Raises :class:`DeviceError` naming the extra to install.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DeviceError(
            f"the Python package for {module} is not installed "
            f"(pip install 'cellvision[{extra}]'): {exc}"
        ) from exc


class DeviceCamera(Camera):
    """A camera read through a vendor SDK on demand (see the module)."""

    def __init__(
        self,
        name: str,
        *,
        intrinsics: Intrinsics | None,
        has_depth: bool,
        reconnect_interval_s: float,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(name, intrinsics=intrinsics, has_depth=has_depth, clock=clock)
        self._configured_intrinsics = intrinsics
        self._reconnect_interval_s = reconnect_interval_s
        self._lock = threading.Lock()
        """Held while the device is used (connect, read, disconnect): one user at a time."""
        self._state_lock = threading.Lock()
        """Guards the fields status() reports, so that it never waits for a slow read."""
        self._connected = False
        self._retry_at: float | None = None  # clock.monotonic() of the next connect attempt
        self._error: str | None = None
        self._failed = False
        self._next_index = 0
        self._reconnects = 0
        self._device_info: dict[str, Any] = {}

    # -- what a subclass provides ----------------------------------------------------------

    @abstractmethod
    def _connect(self) -> None:
        """Open and start the device; raise :class:`DeviceError` with the cause."""

    @abstractmethod
    def _read(self, timeout_s: float) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
        """The next frame (colour, registered depth in mm or None) that the device captured
        after this call started, within ``timeout_s`` seconds; raise :class:`FrameTimeout`
        or :class:`DeviceError`."""

    @abstractmethod
    def _disconnect(self) -> None:
        """Stop and release the device; never raises (the device may already be gone)."""

    def _use_device_intrinsics(self, intrinsics: Intrinsics) -> None:
        """Report ``intrinsics`` (read from the device) unless the configuration gave some."""
        if self._configured_intrinsics is None:
            self._intrinsics = intrinsics

    # -- the camera ------------------------------------------------------------------------

    def open(self) -> None:
        """Connect now, so that the device is armed (a hardware trigger before the first
        request is not lost) and its intrinsics are known; a failure only marks the camera
        down (reported by ``grab`` and ``status``), as for every source.

        After a failure here the first grab tries again at once: a reload that changes the
        camera's settings opens the new camera while the old one still holds the device,
        which it releases when its last request is done.
        """
        if self.closed:
            raise RuntimeError(f"camera {self.name!r} is closed and cannot be reopened")
        with self._lock:
            try:
                self._ensure_connected()
            except CameraUnavailable:
                with self._state_lock:
                    self._retry_at = None

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        # Every read returns a frame captured after it started, with a new index: always
        # newer than ``newer_than``.
        self._check_open()
        started = self._clock.monotonic()
        # Another request's read holds the device: wait for it no longer than this grab may
        # take (a real-time wait: the lock knows no other clock).
        if not self._lock.acquire(timeout=max(timeout_s, 0.0)):
            raise self.unavailable(f"the device is busy with another capture for {timeout_s:.3g} s")
        try:
            self._check_open()
            self._ensure_connected()
            remaining_s = max(timeout_s - (self._clock.monotonic() - started), 0.0)
            # The error's text is kept, not the error: its traceback holds the SDK's objects
            # (a device handle that keeps the device open, or its control) for as long as the
            # answer that carries it lives, so the answer is raised outside the handler.
            late: str | None = None
            lost: str | None = None
            try:
                color, depth = self._read(remaining_s)
            except FrameTimeout as exc:
                late = str(exc)
            except DeviceError as exc:
                lost = str(exc)
            if late is not None:
                raise self.unavailable(late)
            if lost is not None:
                self._go_down(lost)
                raise self.unavailable(self._down_cause())
            try:
                frame = CameraFrame(color, depth, self._clock.time(), self._next_index)
            except ValueError as exc:  # an SDK handed us something we did not ask for
                raise self.unavailable(f"the device gave an unusable frame: {exc}") from None
            with self._state_lock:
                self._next_index += 1
            return frame
        finally:
            self._lock.release()

    def _ensure_connected(self) -> None:
        """Connect if needed; raise ``CameraUnavailable`` while down and not yet due."""
        if self._connected:
            return
        if self._retry_at is not None and self._clock.monotonic() < self._retry_at:
            raise self.unavailable(self._down_cause())
        refused: str | None = None
        try:
            self._connect()
        except DeviceError as exc:
            refused = str(exc)  # the text only: see grab()
        if refused is not None:
            self._disconnect()
            self._go_down(refused)
            raise self.unavailable(self._down_cause())
        with self._state_lock:
            self._connected = True
            self._retry_at = None
            back = self._failed
            if back:
                self._reconnects += 1
                self._failed = False
            self._error = None
        if back:
            log.info("camera %r: the device is back", self.name)

    def _go_down(self, error: str) -> None:
        if error != self._error:
            log.warning("camera %r is unavailable: %s", self.name, error)
        if self._connected:
            self._disconnect()
        with self._state_lock:
            self._connected = False
            self._error = error
            self._failed = True
            self._retry_at = self._clock.monotonic() + self._reconnect_interval_s

    def _down_cause(self) -> str:
        return f"{self._error}; retrying every {self._reconnect_interval_s:g} s"

    def status(self) -> dict[str, Any]:
        with self._state_lock:
            if self.closed:
                state = "closed"
            elif self._connected:
                state = "up"
            else:
                state = "down" if self._failed else "idle"
            return {
                "name": self.name,
                "source": self.source,
                "state": state,
                "connected": self._connected,
                "frames": self._next_index,
                "last_error": self._error,
                "reconnects": self._reconnects,
                **self._device_info,
            }

    def close(self) -> None:
        if self.closed:
            return
        super().close()
        with self._lock:
            if self._connected:
                self._disconnect()
                with self._state_lock:
                    self._connected = False
