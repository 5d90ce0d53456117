"""Camera settings: one frozen dataclass per source kind, validated on construction.

The configuration loader turns a camera's YAML mapping into one of these; a ``ValueError`` names
the bad field (the loader adds the file, line and key path). Lengths in pixels, durations in
seconds. Relative paths are resolved later by :func:`~vision_server.cameras.make_camera` against
the configuration file's directory.
"""

from __future__ import annotations

import ipaddress
import math
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any, Literal

from geometry import CameraIntrinsics

from .mount import CameraMount

__all__ = [
    "ARAVIS_PIXEL_FORMATS",
    "AravisCameraSettings",
    "BACKENDS",
    "SOURCE_NAMES",
    "CameraSettings",
    "FolderCameraSettings",
    "GENICAM_PIXEL_FORMATS",
    "GENICAM_TRIGGERS",
    "GenICamCameraSettings",
    "Intrinsics",
    "OpenCVCameraSettings",
    "RealSenseCameraSettings",
    "RecordingCameraSettings",
    "RequestCameraSettings",
    "SimCameraSettings",
]

BACKENDS = ("any", "v4l2", "ffmpeg", "gstreamer")
"""Values of ``OpenCVCameraSettings.backend`` (``None`` means ``"any"``)."""

# OpenCV accepts 4, 5, 8, 12 or 14 distortion coefficients (k1, k2, p1, p2[, k3[, k4..k6
# [, s1..s4[, tx, ty]]]]).
_DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _positive_int(name: str, value: object) -> int:
    if not _is_int(value) or value <= 0:  # type: ignore[operator]
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)  # type: ignore[call-overload, no-any-return]


def _finite(name: str, value: object, *, positive: bool = False) -> float:
    if not _is_number(value) or not math.isfinite(value):  # type: ignore[arg-type]
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    number = float(value)  # type: ignore[arg-type]
    if positive and number <= 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return number


def _bool(name: str, value: object) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be true or false, got {value!r}")


def _path(name: str, value: object) -> Path:
    if isinstance(value, str):
        if not value:
            raise ValueError(f"{name} must be a non-empty path")
        return Path(value)
    if isinstance(value, PurePath):
        return Path(value)
    raise ValueError(f"{name} must be a path, got {value!r}")


def _relative_pattern(name: str, value: object) -> str:
    """A glob pattern that stays inside the directory it is applied to."""
    if not isinstance(value, str) or not value:
        raise ValueError(f"{name} must be a non-empty glob pattern, got {value!r}")
    pattern = PurePath(value)
    if pattern.is_absolute() or value.startswith(("/", "\\")):
        raise ValueError(f"{name} must be relative to the folder, got {value!r}")
    if ".." in pattern.parts:
        raise ValueError(f"{name} must not contain '..', got {value!r}")
    return value


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a camera, in pixels, for the image size ``width`` x ``height``.

    ``distortion`` is OpenCV's coefficient vector ``(k1, k2, p1, p2[, k3[, ...]])`` with 4, 5,
    8, 12 or 14 entries; 4 entries are padded to 5 with ``k3 = 0``.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "width", _positive_int("width", self.width))
        object.__setattr__(self, "height", _positive_int("height", self.height))
        for name in ("fx", "fy"):
            object.__setattr__(self, name, _finite(name, getattr(self, name), positive=True))
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _finite(name, getattr(self, name)))
        distortion: object = self.distortion
        if isinstance(distortion, str | bytes) or not isinstance(distortion, tuple | list):
            raise ValueError(f"distortion must be a list of numbers, got {self.distortion!r}")
        coeffs = tuple(_finite(f"distortion[{i}]", value) for i, value in enumerate(distortion))
        if len(coeffs) not in _DISTORTION_LENGTHS:
            raise ValueError(
                f"distortion must have 4, 5, 8, 12 or 14 coefficients, got {len(coeffs)}"
            )
        if len(coeffs) == 4:
            coeffs = (*coeffs, 0.0)
        object.__setattr__(self, "distortion", coeffs)

    def to_dict(self) -> dict[str, Any]:
        """The wire form (WELCOME's camera descriptors, FRAMES): SPEC §6.4's object, whose
        coefficients are named ``dist`` (the configuration's ``distortion``), at least the five
        ``k1, k2, p1, p2, k3`` (a four-coefficient model is sent with ``k3 = 0``)."""
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "dist": [*self.distortion, *(0.0,) * (5 - len(self.distortion))],
        }

    def to_geometry(self) -> CameraIntrinsics:
        """The same camera as :class:`geometry.CameraIntrinsics` (5 coefficients).

        Raises ``ValueError`` when a coefficient beyond ``k3`` is non-zero (the geometry
        package implements the 5-coefficient model only).
        """
        extra = self.distortion[5:]
        if any(value != 0.0 for value in extra):
            raise ValueError(
                "distortion has non-zero coefficients beyond k3, which geometry.CameraIntrinsics "
                "does not model"
            )
        k1, k2, p1, p2, k3 = self.distortion[:5]
        return CameraIntrinsics(
            self.width, self.height, self.fx, self.fy, self.cx, self.cy, (k1, k2, p1, p2, k3)
        )

    @classmethod
    def from_geometry(cls, camera: CameraIntrinsics) -> Intrinsics:
        return cls(
            camera.width,
            camera.height,
            camera.fx,
            camera.fy,
            camera.cx,
            camera.cy,
            tuple(camera.dist),
        )


def _intrinsics(value: object) -> None:
    if value is not None and not isinstance(value, Intrinsics):
        raise ValueError(f"intrinsics must be an Intrinsics or None, got {value!r}")


def _mount(value: object) -> None:
    if value is not None and not isinstance(value, CameraMount):
        raise ValueError(f"mount must be a CameraMount or None, got {value!r}")


@dataclass(frozen=True)
class RequestCameraSettings:
    """A camera whose images arrive with each request (the camera on the robot's tool).

    ``depth``: requests may carry a registered depth frame (uint16 mm).
    """

    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None
    depth: bool = False

    def __post_init__(self) -> None:
        _intrinsics(self.intrinsics)
        _mount(self.mount)
        _bool("depth", self.depth)


@dataclass(frozen=True)
class OpenCVCameraSettings:
    """A source read through ``cv2.VideoCapture``.

    ``device``: a device index (``0``), a device path (``/dev/video0``), a stream URL
    (``rtsp://...``, ``http://...``), a GStreamer pipeline (with ``backend: gstreamer``) or a
    video file (relative paths are relative to the configuration file).

    ``width``/``height``/``fps``/``fourcc`` are asked of the device; if the frames that come
    back have another size they are resized to the requested one (one of width/height alone
    keeps the aspect ratio). For a video file ``fps`` overrides the playback rate.

    ``reconnect_interval_s``: pause between attempts to (re)open a source that is down.
    ``read_timeout_s``: open/read timeout given to the backend for streams, and the age beyond
    which the newest frame of a live source counts as stalled.
    ``loop_file``: a video file starts again at its end (else the camera ends there).
    ``intrinsics``: frames of another size than the intrinsics' are refused (the camera is
    down with that cause), since measuring with them would be silently wrong.
    """

    device: int | str
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    backend: str | None = None
    reconnect_interval_s: float = 1.0
    read_timeout_s: float = 2.0
    fourcc: str | None = None
    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None
    loop_file: bool = False

    def __post_init__(self) -> None:
        if _is_int(self.device):
            if self.device < 0:  # type: ignore[operator]
                raise ValueError(f"device index must be >= 0, got {self.device!r}")
        elif isinstance(self.device, str):
            if not self.device.strip():
                raise ValueError("device must be a non-empty string or an index")
        else:
            raise ValueError(f"device must be an index or a string, got {self.device!r}")
        for name in ("width", "height"):
            if getattr(self, name) is not None:
                _positive_int(name, getattr(self, name))
        if self.fps is not None:
            object.__setattr__(self, "fps", _finite("fps", self.fps, positive=True))
        if self.backend is not None and self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {list(BACKENDS)}, got {self.backend!r}")
        for name in ("reconnect_interval_s", "read_timeout_s"):
            object.__setattr__(self, name, _finite(name, getattr(self, name), positive=True))
        if self.fourcc is not None and (
            not isinstance(self.fourcc, str) or len(self.fourcc) != 4 or not self.fourcc.isascii()
        ):
            raise ValueError(f"fourcc must be 4 ASCII characters, got {self.fourcc!r}")
        _intrinsics(self.intrinsics)
        _mount(self.mount)
        _bool("loop_file", self.loop_file)
        if self.intrinsics is not None:
            for name in ("width", "height"):
                wanted = getattr(self, name)
                if wanted is not None and wanted != getattr(self.intrinsics, name):
                    raise ValueError(
                        f"{name} is {wanted} but intrinsics.{name} is "
                        f"{getattr(self.intrinsics, name)}: intrinsics must match the frame size"
                    )


@dataclass(frozen=True)
class FolderCameraSettings:
    """Images from a directory, for replay.

    Files matching ``glob`` (relative to ``path``; ``**`` recurses) are taken in natural sort
    order (``img2`` before ``img10``). ``mode``: ``cycle`` starts again after the last image,
    ``once`` stops there. ``depth_glob``: depth PNGs (uint16 mm) paired with the colour images
    by file stem when every colour image has a depth file of the same stem, else by sorted
    order. ``color``: ``gray`` or ``bgr`` converts on reading, ``unchanged`` keeps gray as gray
    and colour as BGR (an alpha channel is dropped).
    """

    path: Path
    glob: str = "*.png"
    mode: Literal["cycle", "once"] = "cycle"
    depth_glob: str | None = None
    color: Literal["gray", "bgr", "unchanged"] = "unchanged"
    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", _path("path", self.path))
        _relative_pattern("glob", self.glob)
        if self.mode not in ("cycle", "once"):
            raise ValueError(f"mode must be 'cycle' or 'once', got {self.mode!r}")
        if self.depth_glob is not None:
            _relative_pattern("depth_glob", self.depth_glob)
        if self.color not in ("gray", "bgr", "unchanged"):
            raise ValueError(f"color must be 'gray', 'bgr' or 'unchanged', got {self.color!r}")
        _intrinsics(self.intrinsics)
        _mount(self.mount)


@dataclass(frozen=True)
class SimCameraSettings:
    """A camera of the simulated cell.

    ``scene``: the scene YAML; ``camera``: the camera's name in it; ``state_file``: the
    world-state file shared with the process that moves the robot (see simulation/README.md);
    ``seed``: the simulation seed; ``intrinsics``: default the scene camera's own.
    """

    scene: Path
    camera: str
    state_file: Path | None = None
    seed: int = 0
    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "scene", _path("scene", self.scene))
        if not isinstance(self.camera, str) or not self.camera:
            raise ValueError(f"camera must be a non-empty name, got {self.camera!r}")
        if self.state_file is not None:
            object.__setattr__(self, "state_file", _path("state_file", self.state_file))
        if not _is_int(self.seed) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        _intrinsics(self.intrinsics)
        _mount(self.mount)


def _serial(value: object) -> None:
    if value is not None and (not isinstance(value, str) or not value.strip()):
        raise ValueError(
            f"serial must be a non-empty string (quote a numeric serial in YAML), got {value!r}"
        )


def _intrinsics_match(intrinsics: Intrinsics | None, width: int, height: int) -> None:
    if intrinsics is not None and (intrinsics.width, intrinsics.height) != (width, height):
        raise ValueError(
            f"intrinsics are for {intrinsics.width}x{intrinsics.height} but the camera is set "
            f"to {width}x{height}: intrinsics must match the frame size"
        )


@dataclass(frozen=True)
class RealSenseCameraSettings:
    """An Intel RealSense RGB-D camera through pyrealsense2 (the ``realsense`` extra).

    ``serial``: the device's serial number (a string; quote it in YAML); None takes the only
    connected device and refuses to guess between several. ``width``/``height``/``fps``: the
    colour stream's mode, which the device must offer (default 640x480 at 30). ``depth``: also
    stream depth, aligned to the colour image and converted to uint16 mm with the device's
    depth scale.
    ``depth_width``/``depth_height``: the depth stream's mode when it differs from the
    colour's (e.g. 1280x720 depth under 1920x1080 colour). ``reconnect_interval_s``: pause
    before connecting again to a device that was absent or lost. ``intrinsics``: default the
    device's own colour intrinsics.

    ``playback``: play a RealSense recording (the SDK's own file, ``*.db3`` or ``*.bag``;
    relative to the configuration file) through the SDK instead of a device; every grab takes
    the recording's next frame. ``width``/``height`` (and ``depth_width``/``depth_height``), when
    given, must be the recorded streams' sizes (absent: whatever the recording holds); ``fps``
    is not used. At the recording's end
    the camera ends (every grab says so); it does not loop (see the realsense module).
    ``serial`` is not used with ``playback``.
    """

    serial: str | None = None
    width: int | None = None
    height: int | None = None
    fps: int = 30
    depth: bool = True
    depth_width: int | None = None
    depth_height: int | None = None
    reconnect_interval_s: float = 1.0
    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None
    playback: Path | None = None

    def __post_init__(self) -> None:
        _serial(self.serial)
        if self.playback is not None:
            object.__setattr__(self, "playback", _path("playback", self.playback))
            if self.serial is not None:
                raise ValueError(
                    "serial and playback exclude each other: a recording plays without a device"
                )
        if (self.width is None) != (self.height is None):
            raise ValueError("give both width and height, or neither")
        if self.width is None and self.playback is None:
            # A device's default mode; a playback's default is the recording's own size.
            object.__setattr__(self, "width", 640)
            object.__setattr__(self, "height", 480)
        for name in ("width", "height"):
            if getattr(self, name) is not None:
                _positive_int(name, getattr(self, name))
        _positive_int("fps", self.fps)
        if (self.depth_width is None) != (self.depth_height is None):
            raise ValueError("give both depth_width and depth_height, or neither")
        for name in ("depth_width", "depth_height"):
            if getattr(self, name) is not None:
                _positive_int(name, getattr(self, name))
        _bool("depth", self.depth)
        object.__setattr__(
            self,
            "reconnect_interval_s",
            _finite("reconnect_interval_s", self.reconnect_interval_s, positive=True),
        )
        _intrinsics(self.intrinsics)
        _mount(self.mount)
        if self.width is not None and self.height is not None:
            _intrinsics_match(self.intrinsics, self.width, self.height)


GENICAM_PIXEL_FORMATS = (
    "Mono8",
    "Mono10",
    "Mono12",
    "Mono16",
    "BayerRG8",
    "BayerGR8",
    "BayerGB8",
    "BayerBG8",
)
"""Values of ``GenICamCameraSettings.pixel_format`` (GenICam's SFNC names, unpacked)."""

GENICAM_TRIGGERS = ("free_run", "software", "hardware")
"""Values of ``GenICamCameraSettings.trigger``."""


def _trigger_source(trigger: object, source: object) -> str | None:
    """A GenICam camera's ``trigger`` checked, and its ``trigger_source``: the configured line
    (only with a hardware trigger), ``Line0`` for a hardware trigger without one, else None."""
    if trigger not in GENICAM_TRIGGERS:
        raise ValueError(f"trigger must be one of {list(GENICAM_TRIGGERS)}, got {trigger!r}")
    if source is None:
        return "Line0" if trigger == "hardware" else None
    if trigger != "hardware":
        raise ValueError("trigger_source is only used with trigger: hardware")
    if not isinstance(source, str) or not source.strip():
        raise ValueError(f"trigger_source must be a line name such as 'Line0', got {source!r}")
    return source


@dataclass(frozen=True)
class GenICamCameraSettings:
    """A GenICam camera (GigE Vision, USB3 Vision) through harvesters (the ``genicam`` extra).

    ``cti``: the GenTL producer (.cti file) of the camera's vendor, relative to the
    configuration file. ``serial``: the device's serial number (a string); None takes the
    only device the producer sees. ``pixel_format``: Mono8/10/12/16 (frames are scaled to
    8 bits) or Bayer*8 (demosaiced to BGR). ``exposure_us``: ExposureTime in microseconds;
    ``gain_db``: Gain in dB; None leaves the device's value. ``trigger``: ``free_run`` (a grab
    takes the newest frame), ``software`` (a grab fires TriggerSoftware) or ``hardware`` (a
    grab takes the next frame triggered on ``trigger_source``, e.g. ``Line0``).
    ``reconnect_interval_s``: pause before connecting again to a device that was absent or
    lost. The device's own ranges are checked when it connects.
    """

    cti: Path
    serial: str | None = None
    pixel_format: str = "Mono8"
    exposure_us: float | None = None
    gain_db: float | None = None
    trigger: str = "free_run"
    trigger_source: str | None = None
    reconnect_interval_s: float = 1.0
    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "cti", _path("cti", self.cti))
        if self.cti.suffix.lower() != ".cti":
            raise ValueError(f"cti must name a GenTL producer file (*.cti), got {str(self.cti)!r}")
        _serial(self.serial)
        if self.pixel_format not in GENICAM_PIXEL_FORMATS:
            raise ValueError(
                f"pixel_format must be one of {list(GENICAM_PIXEL_FORMATS)}, "
                f"got {self.pixel_format!r}"
            )
        if self.exposure_us is not None:
            object.__setattr__(
                self, "exposure_us", _finite("exposure_us", self.exposure_us, positive=True)
            )
        if self.gain_db is not None:
            object.__setattr__(self, "gain_db", _finite("gain_db", self.gain_db))
        object.__setattr__(
            self, "trigger_source", _trigger_source(self.trigger, self.trigger_source)
        )
        object.__setattr__(
            self,
            "reconnect_interval_s",
            _finite("reconnect_interval_s", self.reconnect_interval_s, positive=True),
        )
        _intrinsics(self.intrinsics)
        _mount(self.mount)


@dataclass(frozen=True)
class RecordingCameraSettings:
    """A recording made by ``vision-server record`` (see :mod:`vision_server.cameras.recording`),
    replayed frame by frame.

    ``path``: the recording's directory (the one holding ``recording.json``), relative to the
    configuration file. ``loop``: start again after the last frame; else the camera ends there
    (CAMERA_UNAVAILABLE naming the recording and its frame count). ``intrinsics``: default the
    recording's own (those the camera had when it was recorded).
    """

    path: Path
    loop: bool = False
    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", _path("path", self.path))
        _bool("loop", self.loop)
        _intrinsics(self.intrinsics)
        _mount(self.mount)


ARAVIS_PIXEL_FORMATS = (*GENICAM_PIXEL_FORMATS, "RGB8", "BGR8")
"""Values of ``AravisCameraSettings.pixel_format`` (GenICam's SFNC names, unpacked)."""


def _region(value: object) -> tuple[int, int, int, int] | None:
    if value is None:
        return None
    if (
        not isinstance(value, (list, tuple))
        or len(value) != 4
        or not all(_is_int(v) for v in value)
        or min(value) < 0
        or value[2] < 1
        or value[3] < 1
    ):
        raise ValueError(
            "region must be [x, y, width, height] in pixels (offsets >= 0, sizes >= 1), "
            f"got {value!r}"
        )
    return (int(value[0]), int(value[1]), int(value[2]), int(value[3]))


@dataclass(frozen=True)
class AravisCameraSettings:
    """A GigE Vision or USB3 Vision camera through Aravis (the ``aravis`` extra: PyGObject,
    with Debian's ``gir1.2-aravis-0.8``); no vendor GenTL producer is needed.

    The device: ``serial`` (its serial number), ``device_id`` (Aravis' ID, e.g.
    ``Basler-21234567``) or ``address`` (its IPv4 address, opened directly without discovery,
    also across subnets), at most one; none takes the only device discovered.
    ``pixel_format``: Mono8/10/12/16 (scaled to 8 bits), Bayer*8 (demosaiced to BGR), RGB8 or
    BGR8. ``exposure_us``: ExposureTime in microseconds; ``gain_db``: Gain in dB;
    ``region``: [x, y, width, height] in sensor pixels; ``frame_rate_hz``: AcquisitionFrameRate
    (free run: the rate; triggered: on most devices the most frames a second it accepts);
    None leaves the device's value for each. ``trigger``:
    ``free_run``, ``software`` or ``hardware`` (on ``trigger_source``, default ``Line0``).
    ``packet_size``: the GVSP packet size in bytes, or None to negotiate the largest the
    path carries; ``packet_resend``: ask the device to resend lost packets. ``buffers``: frames
    the stream holds (memory: ``buffers`` x the frame size). Every value is checked against the
    device's own GenICam range or entries when it connects; a refusal names the feature and
    its range. ``reconnect_interval_s``: pause before connecting again to a device that was
    absent, lost or controlled by another application.
    """

    serial: str | None = None
    device_id: str | None = None
    address: str | None = None
    pixel_format: str = "Mono8"
    exposure_us: float | None = None
    gain_db: float | None = None
    region: tuple[int, int, int, int] | None = None
    frame_rate_hz: float | None = None
    trigger: str = "free_run"
    trigger_source: str | None = None
    packet_size: int | None = None
    packet_resend: bool = True
    buffers: int = 8
    reconnect_interval_s: float = 1.0
    intrinsics: Intrinsics | None = None
    mount: CameraMount | None = None

    def __post_init__(self) -> None:
        _serial(self.serial)
        chosen = [k for k in ("serial", "device_id", "address") if getattr(self, k) is not None]
        if len(chosen) > 1:
            raise ValueError(f"give at most one of serial, device_id and address, got {chosen}")
        for key in ("device_id", "address"):
            value = getattr(self, key)
            if value is not None and (not isinstance(value, str) or not value.strip()):
                raise ValueError(f"{key} must be a non-empty string, got {value!r}")
        if self.address is not None:
            try:
                ipaddress.IPv4Address(self.address)
            except ValueError:
                raise ValueError(
                    f"address must be the device's IPv4 address, got {self.address!r}"
                ) from None
        if self.pixel_format not in ARAVIS_PIXEL_FORMATS:
            raise ValueError(
                f"pixel_format must be one of {list(ARAVIS_PIXEL_FORMATS)}, "
                f"got {self.pixel_format!r}"
            )
        for key in ("exposure_us", "frame_rate_hz"):
            if getattr(self, key) is not None:
                object.__setattr__(self, key, _finite(key, getattr(self, key), positive=True))
        if self.gain_db is not None:
            object.__setattr__(self, "gain_db", _finite("gain_db", self.gain_db))
        object.__setattr__(self, "region", _region(self.region))
        object.__setattr__(
            self, "trigger_source", _trigger_source(self.trigger, self.trigger_source)
        )
        if self.packet_size is not None:
            _positive_int("packet_size", self.packet_size)
            if not 576 <= self.packet_size <= 65536:
                raise ValueError(
                    f"packet_size must be 576 to 65536 bytes (or absent: negotiated), "
                    f"got {self.packet_size}"
                )
        _bool("packet_resend", self.packet_resend)
        _positive_int("buffers", self.buffers)
        if self.buffers > 64:
            raise ValueError(f"buffers must be 1 to 64, got {self.buffers}")
        object.__setattr__(
            self,
            "reconnect_interval_s",
            _finite("reconnect_interval_s", self.reconnect_interval_s, positive=True),
        )
        _intrinsics(self.intrinsics)
        _mount(self.mount)
        if self.region is not None:
            _intrinsics_match(self.intrinsics, self.region[2], self.region[3])


CameraSettings = (
    RequestCameraSettings
    | OpenCVCameraSettings
    | FolderCameraSettings
    | SimCameraSettings
    | RealSenseCameraSettings
    | GenICamCameraSettings
    | AravisCameraSettings
    | RecordingCameraSettings
)

SOURCE_NAMES: dict[str, type[CameraSettings]] = {
    "request": RequestCameraSettings,
    "opencv": OpenCVCameraSettings,
    "folder": FolderCameraSettings,
    "sim": SimCameraSettings,
    "realsense": RealSenseCameraSettings,
    "genicam": GenICamCameraSettings,
    "aravis": AravisCameraSettings,
    "recording": RecordingCameraSettings,
}
"""The ``source:`` value of a camera in the configuration -> its settings class."""
