"""The ``realsense`` source: an Intel RealSense RGB-D camera through pyrealsense2.

pyrealsense2 is an optional extra (``pip install 'cellvision[realsense]'``), imported when the
camera first connects (:func:`vision_server.cameras.device.import_sdk`). A grab returns the
colour image (BGR) and, with ``depth``, the depth image aligned to the colour image by the SDK
(``rs.align``) and converted from the device's units to uint16 millimetres with the device's
depth scale (a D405 counts 0.1 mm, a D435 1 mm). The camera's intrinsics are the colour
stream's, read from the device, unless the configuration gives its own.

Errors: no device, an unknown serial, several devices and no serial, a stream mode the device
does not offer, a distortion model OpenCV does not share: the camera is down with that cause
(retried every ``reconnect_interval_s``). librealsense reports both a late frame and an
unplugged device as "Frame didn't arrive within ..."; the device list tells them apart.

Not tried on a device: see README.md ("Real devices").
"""

from __future__ import annotations

import contextlib
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .clock import Clock
from .device import DeviceCamera, DeviceError, FrameTimeout, import_sdk
from .settings import Intrinsics, RealSenseCameraSettings

__all__ = ["RealSenseCamera", "depth_to_mm"]

_MAX_STALE_FRAMESETS = 16
"""Framesets dropped at most before a grab waits for a fresh one (the SDK queues a few)."""


def depth_to_mm(raw: NDArray[np.uint16], depth_scale_m: float) -> NDArray[np.uint16]:
    """Depth in device units (``raw``, 0 = none) -> uint16 millimetres, rounded, clipped at
    65535 mm. ``depth_scale_m``: metres per device unit."""
    factor = depth_scale_m * 1000.0
    if abs(factor - 1.0) < 1e-9:
        return np.array(raw, dtype=np.uint16)
    scaled = np.rint(raw.astype(np.float64) * factor)
    return np.clip(scaled, 0, 65535).astype(np.uint16)


class RealSenseCamera(DeviceCamera):
    """An Intel RealSense camera (see the module)."""

    source = "realsense"

    def __init__(
        self, name: str, settings: RealSenseCameraSettings, *, clock: Clock | None = None
    ) -> None:
        super().__init__(
            name,
            intrinsics=settings.intrinsics,
            has_depth=settings.depth,
            reconnect_interval_s=settings.reconnect_interval_s,
            clock=clock,
        )
        self.settings = settings
        self._rs: ModuleType | None = None
        self._context: Any = None
        self._pipeline: Any = None
        self._align: Any = None
        self._serial: str | None = None
        self._depth_scale_m = 0.001

    # -- connect ---------------------------------------------------------------------------

    def _connect(self) -> None:
        rs = self._rs = import_sdk("pyrealsense2", extra="realsense")
        s = self.settings
        try:
            self._context = rs.context()
            serial, model = self._pick_device(rs)
            config = rs.config()
            config.enable_device(serial)
            config.enable_stream(rs.stream.color, s.width, s.height, rs.format.bgr8, s.fps)
            depth_size = (s.depth_width or s.width, s.depth_height or s.height)
            if s.depth:
                config.enable_stream(rs.stream.depth, *depth_size, rs.format.z16, s.fps)
            pipeline = rs.pipeline(self._context)
            if not config.can_resolve(rs.pipeline_wrapper(pipeline)):
                modes = f"colour {s.width}x{s.height}"
                if s.depth:
                    modes += f" and depth {depth_size[0]}x{depth_size[1]}"
                raise DeviceError(
                    f"RealSense {model} (serial {serial}) does not offer {modes} at {s.fps} fps"
                )
            profile = pipeline.start(config)
        except RuntimeError as exc:  # pyrealsense2 raises RuntimeError for device errors
            raise DeviceError(f"starting the RealSense device failed: {exc}") from exc
        self._pipeline, self._serial = pipeline, serial
        self._device_info = {"serial": serial, "model": model}
        try:
            if s.depth:
                self._depth_scale_m = float(
                    profile.get_device().first_depth_sensor().get_depth_scale()
                )
                self._device_info["depth_scale_m"] = self._depth_scale_m
                self._align = rs.align(rs.stream.color)
            stream = profile.get_stream(rs.stream.color).as_video_stream_profile()
            intrinsics = self._intrinsics_of(rs, stream.get_intrinsics())
        except RuntimeError as exc:
            raise DeviceError(f"reading the RealSense {model}'s streams failed: {exc}") from exc
        if intrinsics is not None:
            self._use_device_intrinsics(intrinsics)

    def _pick_device(self, rs: ModuleType) -> tuple[str, str]:
        """(serial, model name) of the configured device among the connected ones."""
        found = {
            str(dev.get_info(rs.camera_info.serial_number)): str(dev.get_info(rs.camera_info.name))
            for dev in self._context.query_devices()
        }
        listed = ", ".join(sorted(found)) or "none"
        wanted = self.settings.serial
        if wanted is None:
            if len(found) != 1:
                what = "no RealSense device is connected" if not found else "several are"
                raise DeviceError(f"{what} (serials: {listed}); set serial to choose one")
            return next(iter(found.items()))
        if wanted not in found:
            raise DeviceError(f"no RealSense device with serial {wanted} (connected: {listed})")
        return wanted, found[wanted]

    def _intrinsics_of(self, rs: ModuleType, k: Any) -> Intrinsics | None:
        """The colour stream's intrinsics in our form; None when the configuration gives them.

        RealSense's Brown-Conrady coefficients are OpenCV's ``k1, k2, p1, p2, k3``; the other
        models are accepted only with zero coefficients (as D400 colour streams report them),
        since reading them as OpenCV's would be silently wrong.
        """
        if self._configured_intrinsics is not None:
            return None
        coeffs = tuple(float(c) for c in k.coeffs)
        if k.model != rs.distortion.brown_conrady and any(coeffs):
            raise DeviceError(
                f"the colour stream's distortion model {k.model} is not OpenCV's (coefficients "
                f"{list(coeffs)}): give the camera's intrinsics in the configuration"
            )
        return Intrinsics(
            int(k.width), int(k.height), float(k.fx), float(k.fy), float(k.ppx), float(k.ppy),
            coeffs if k.model == rs.distortion.brown_conrady else (0.0,) * 5,
        )  # fmt: skip

    # -- read ------------------------------------------------------------------------------

    def _read(self, timeout_s: float) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
        pipeline = self._pipeline
        # Latest-frame semantics: framesets queued before this grab are old moments.
        for _ in range(_MAX_STALE_FRAMESETS):
            if not pipeline.poll_for_frames():
                break
        try:
            frames = pipeline.wait_for_frames(max(1, round(timeout_s * 1000)))
        except RuntimeError as exc:
            if not self._still_connected():
                raise DeviceError(f"RealSense device {self._serial} was disconnected") from exc
            raise FrameTimeout(
                f"no frame from RealSense {self._serial} within {timeout_s:.3g} s ({exc})"
            ) from exc
        if self.settings.depth:
            frames = self._align.process(frames)
        color_frame = frames.get_color_frame()
        if not color_frame:
            raise FrameTimeout(f"RealSense {self._serial} gave a frameset without colour")
        color = np.array(np.asanyarray(color_frame.get_data()), dtype=np.uint8)
        if not self.settings.depth:
            return color, None
        depth_frame = frames.get_depth_frame()
        if not depth_frame:
            raise FrameTimeout(f"RealSense {self._serial} gave a frameset without depth")
        raw = np.asanyarray(depth_frame.get_data())
        if raw.dtype != np.uint16:
            raise DeviceError(f"depth frames are {raw.dtype}, expected z16 (uint16)")
        return color, depth_to_mm(raw, self._depth_scale_m)

    def _still_connected(self) -> bool:
        rs = self._rs
        assert rs is not None
        try:
            serials = {
                str(dev.get_info(rs.camera_info.serial_number))
                for dev in self._context.query_devices()
            }
        except RuntimeError:
            return False
        return self._serial in serials

    def _disconnect(self) -> None:
        pipeline, self._pipeline = self._pipeline, None
        self._align = None
        if pipeline is not None:
            with contextlib.suppress(RuntimeError):  # already stopped, or the device is gone
                pipeline.stop()
