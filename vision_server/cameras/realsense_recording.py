"""Writing RealSense recordings: :class:`RealSenseRecorder`.

A recording is the SDK's own file, written by librealsense itself: frames are handed to a
``pyrealsense2.software_device`` (a device made in software, with a colour and a depth sensor)
whose streams an ``rs.recorder`` writes down. pyrealsense2 2.59 writes rosbag2 (a SQLite
``.db3`` file with one topic per stream's images, ``camera_info`` and metadata, the sensors'
options such as ``Depth_Units``, and the depth-to-colour extrinsic on ``/tf_static``); the
recorder refuses any other file name extension. The same SDK plays it back as it would a
device: ``source: realsense`` with ``playback: FILE`` (see :mod:`.realsense`), the
``realsense-viewer`` and ``rs.config().enable_device_from_file``.

What a recording holds:

- colour: ``bgr8``, ``width`` x ``height`` at ``fps``, with ``intrinsics`` (pixels, OpenCV's
  pinhole model; the Brown-Conrady coefficients are OpenCV's ``k1, k2, p1, p2, k3``);
- depth (with ``depth=True``): ``z16`` in device units of ``depth_scale_m`` metres (a D405
  counts 0.0001 m, a D435 0.001 m), at the size of ``depth_intrinsics`` (default: the
  colour's), with the ``depth_units`` option of the depth sensor set to ``depth_scale_m``;
- the extrinsic depth -> colour: identity (no rotation, zero translation). The depth frames
  are taken to be seen from the colour camera's optical centre, as the simulated cell's RGB-D
  camera renders them; the two streams may still differ in intrinsics and size, and the
  SDK's ``rs.align`` then resamples the depth onto the colour image on playback.
- per frame: a frame number (1, 2, 3, ... in the order of :meth:`RealSenseRecorder.add`,
  the same for the colour and the depth frame of one ``add``) and a timestamp in the SDK's
  milliseconds, domain ``system_time`` (milliseconds since the epoch): ``time_s * 1000``.

pyrealsense2 is the optional ``realsense`` extra, imported when a recorder is made.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType, TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .settings import Intrinsics

__all__ = ["RealSenseRecorder", "mm_to_depth_units"]


def mm_to_depth_units(depth_mm: NDArray[np.uint16], depth_scale_m: float) -> NDArray[np.uint16]:
    """uint16 millimetres (0 = no depth) -> z16 device units of ``depth_scale_m`` metres,
    rounded. A depth the 16 bits cannot hold at that scale (beyond 6.5535 m at 0.0001 m)
    becomes 0, no depth, as a device reports a point out of its range."""
    units_per_mm = 1.0 / (depth_scale_m * 1000.0)
    if abs(units_per_mm - 1.0) < 1e-9:
        return np.array(depth_mm, dtype=np.uint16)
    scaled = np.rint(depth_mm.astype(np.float64) * units_per_mm)
    scaled[scaled > 65535] = 0
    return scaled.astype(np.uint16)


def _import_pyrealsense2() -> ModuleType:
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as exc:
        raise ImportError(
            f"writing a RealSense recording needs pyrealsense2 "
            f"(pip install 'cellvision[realsense]'): {exc}"
        ) from exc


def _sdk_intrinsics(rs: ModuleType, intrinsics: Intrinsics, what: str) -> Any:
    """``intrinsics`` as the SDK's ``rs.intrinsics`` (Brown-Conrady = OpenCV's 5 terms)."""
    extra = intrinsics.distortion[5:]
    if any(value != 0.0 for value in extra):
        raise ValueError(
            f"{what} have distortion coefficients beyond k3, which a RealSense recording "
            "cannot hold (its Brown-Conrady model has k1, k2, p1, p2, k3)"
        )
    k = rs.intrinsics()
    k.width, k.height = intrinsics.width, intrinsics.height
    k.fx, k.fy, k.ppx, k.ppy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    k.model = rs.distortion.brown_conrady
    k.coeffs = [float(c) for c in intrinsics.distortion[:5]]
    return k


class RealSenseRecorder:
    """Write a RealSense recording (the SDK's own format, see the module) frame by frame.

    ``path``: the file to write, ``*.db3`` (the SDK 2.59 writes rosbag2 and refuses other
    names); an existing file is replaced. ``width``/``height``/``fps``: the colour stream's
    mode (pixels, frames per second). ``intrinsics``: the colour stream's, for
    ``width`` x ``height``. ``depth_intrinsics``: the depth stream's (its size is the depth
    frames' size); default the colour's. ``depth_scale_m``: metres per depth unit in the file.
    ``depth``: record a depth stream.

    Use it as a context manager, or call :meth:`close`: the file is complete only then.
    Raises ``ValueError`` for arguments that do not fit together, ``ImportError`` without
    pyrealsense2, ``RuntimeError`` when the SDK refuses (for instance an unwritable path).
    """

    def __init__(
        self,
        path: Path,
        *,
        width: int,
        height: int,
        fps: int,
        intrinsics: Intrinsics,
        depth_intrinsics: Intrinsics | None = None,
        depth_scale_m: float = 0.001,
        depth: bool = True,
    ) -> None:
        path = Path(path)
        if path.suffix != ".db3":
            raise ValueError(
                f"a RealSense recording must be named *.db3 (pyrealsense2 2.59 writes rosbag2), "
                f"got {path.name!r}"
            )
        for name, value in (("width", width), ("height", height), ("fps", fps)):
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if (intrinsics.width, intrinsics.height) != (width, height):
            raise ValueError(
                f"intrinsics are for {intrinsics.width}x{intrinsics.height} but the colour "
                f"stream is {width}x{height}"
            )
        if not (isinstance(depth_scale_m, int | float) and 0.0 < depth_scale_m < 1.0):
            raise ValueError(f"depth_scale_m must be in (0, 1) metres, got {depth_scale_m!r}")
        self.path = path
        self.width, self.height, self.fps = width, height, fps
        self.intrinsics = intrinsics
        self.depth_intrinsics = (depth_intrinsics or intrinsics) if depth else None
        self.depth_scale_m = float(depth_scale_m)
        self.depth = depth
        self.frames = 0
        """Frames written so far."""
        self._last_time_ms: float | None = None
        rs = self._rs = _import_pyrealsense2()

        device = rs.software_device()
        device.register_info(rs.camera_info.name, "cellvision RealSenseRecorder")
        device.register_info(rs.camera_info.serial_number, "cellvision-recording")
        device.register_info(rs.camera_info.product_line, "D400")
        # The depth sensor first: on playback the SDK then delivers a recording's first
        # colour frame with its depth (added second, it loses the first pair).
        self._depth_sensor: Any = None
        self._depth_profile: Any = None
        if self.depth_intrinsics is not None:
            self._depth_sensor = device.add_sensor("Depth")
            self._depth_sensor.add_read_only_option(rs.option.depth_units, self.depth_scale_m)
            self._depth_profile = self._depth_sensor.add_video_stream(
                self._stream(
                    rs.stream.depth,
                    rs.format.z16,
                    2,
                    self.depth_intrinsics,
                    uid=2,
                    what="depth_intrinsics",
                )  # fmt: skip
            ).as_video_stream_profile()
        self._color_sensor = device.add_sensor("Color")
        self._color_profile = self._color_sensor.add_video_stream(
            self._stream(rs.stream.color, rs.format.bgr8, 3, intrinsics, uid=1, what="intrinsics")
        ).as_video_stream_profile()
        if self._depth_profile is not None:
            depth_to_color = rs.extrinsics()
            depth_to_color.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            depth_to_color.translation = [0.0, 0.0, 0.0]
            self._depth_profile.register_extrinsics_to(self._color_profile, depth_to_color)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.unlink(missing_ok=True)
        # Uncompressed (the third argument): nothing to decode on playback. (The SDK's
        # compression came back bit for bit too, in a trial with 2.59.1.)
        self._recorder: Any = rs.recorder(str(path), device, False)
        self._device: Any = device
        self._recording_sensors: list[Any] = []
        try:
            for sensor in self._recorder.query_sensors():
                sensor.open(sensor.get_stream_profiles()[0])
                sensor.start(lambda frame: None)  # the recorder writes what passes through
                self._recording_sensors.append(sensor)
        except RuntimeError:
            self.close()
            raise

    def _stream(
        self, kind: Any, fmt: Any, bpp: int, intrinsics: Intrinsics, *, uid: int, what: str
    ) -> Any:
        stream = self._rs.video_stream()
        stream.type, stream.index, stream.uid = kind, 0, uid
        stream.width, stream.height, stream.fps = intrinsics.width, intrinsics.height, self.fps
        stream.bpp, stream.fmt = bpp, fmt
        stream.intrinsics = _sdk_intrinsics(self._rs, intrinsics, what)
        return stream

    def add(
        self, color_bgr: NDArray[np.uint8], depth_mm: NDArray[np.uint16] | None, time_s: float
    ) -> None:
        """Write one frame: ``color_bgr`` (H, W, 3) BGR uint8 (a gray (H, W) image is
        written as BGR), ``depth_mm`` (h, w) uint16 millimetres (0 = no depth) at the depth
        stream's size, as seen by the depth stream (None only without depth), and
        ``time_s``, the capture time in seconds since the epoch (``CameraFrame.timestamp``),
        which must increase from frame to frame. The depth is stored rounded to the depth
        scale (see :func:`mm_to_depth_units`)."""
        if self._recorder is None:
            raise ValueError(f"the recording {self.path.name} is closed")
        color = np.asarray(color_bgr)
        if color.dtype != np.uint8:
            raise ValueError(f"color_bgr must be uint8, got {color.dtype}")
        if color.ndim == 2:
            color = np.repeat(color[:, :, np.newaxis], 3, axis=2)
        if color.shape != (self.height, self.width, 3):
            raise ValueError(
                f"color_bgr must be ({self.height}, {self.width}, 3), got {color.shape}"
            )
        time_ms = float(time_s) * 1000.0
        if not np.isfinite(time_ms):
            raise ValueError(f"time_s must be a finite number, got {time_s!r}")
        if self._last_time_ms is not None and time_ms <= self._last_time_ms:
            raise ValueError(
                f"time_s must increase: {time_s!r} s after {self._last_time_ms / 1000.0!r} s"
            )
        raw: NDArray[np.uint16] | None = None
        if self.depth_intrinsics is None:
            if depth_mm is not None:
                raise ValueError("this recording has no depth stream (depth=False)")
        else:
            if depth_mm is None:
                raise ValueError("this recording has a depth stream: give depth_mm")
            depth_arr = np.asarray(depth_mm)
            size = (self.depth_intrinsics.height, self.depth_intrinsics.width)
            if depth_arr.dtype != np.uint16 or depth_arr.shape != size:
                raise ValueError(
                    f"depth_mm must be {size} uint16 millimetres, got {depth_arr.shape} "
                    f"{depth_arr.dtype}"
                )
            raw = mm_to_depth_units(depth_arr, self.depth_scale_m)
        number = self.frames + 1
        # Depth first, colour last: the colour frame completes the pair on playback.
        if raw is not None:
            frame = self._frame(raw, 2, time_ms, number, self._depth_profile)
            frame.depth_units = self.depth_scale_m
            self._depth_sensor.on_video_frame(frame)
        self._color_sensor.on_video_frame(
            self._frame(color, 3, time_ms, number, self._color_profile)
        )
        self.frames = number
        self._last_time_ms = time_ms

    def _frame(
        self, pixels: NDArray[Any], bpp: int, time_ms: float, number: int, profile: Any
    ) -> Any:
        rs = self._rs
        frame = rs.software_video_frame()
        frame.pixels = np.ascontiguousarray(pixels)  # copied by the SDK's Python binding
        frame.stride = int(pixels.shape[1]) * bpp
        frame.bpp = bpp
        frame.timestamp = time_ms
        frame.domain = rs.timestamp_domain.system_time
        frame.frame_number = number
        frame.profile = profile
        return frame

    def close(self) -> None:
        """Stop the streams and finish the file. Idempotent."""
        if self._recorder is None:
            return
        sensors, self._recording_sensors = self._recording_sensors, []
        for sensor in sensors:
            sensor.stop()
            sensor.close()
        del sensors
        # librealsense finishes the file when the recording device is destroyed: drop every
        # handle on it.
        self._recorder = None
        self._device = None
        self._color_sensor = self._depth_sensor = None
        self._color_profile = self._depth_profile = None

    def __enter__(self) -> RealSenseRecorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
