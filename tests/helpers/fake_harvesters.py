"""Fake ``harvesters.core`` and ``genicam`` modules that behave like GenICam cameras on a
network behind a GenTL producer.

:func:`fake_harvesters` returns ``(modules, network)``: put each of ``modules`` in
``sys.modules`` under its name (``monkeypatch.setitem``) and drive the cameras through the
:class:`Network`: unplug and plug them, pulse their trigger lines, queue stale buffers.

What it copies from harvesters 1.4 and the genicam binding:

- ``Harvester().add_file(cti)`` then ``update()`` fills ``device_info_list`` (serial, model)
  with the plugged cameras; a producer path that is not a file lists nothing.
- ``create({"serial_number": s})`` raises ValueError for an unknown device, and for a device
  that is already open (GenTL's exclusive access) until ``destroy()``.
- The node map: enumerations (``symbolics``; a value not among them raises
  ``genapi.InvalidArgumentException``), numbers (``min``/``max``; outside raises
  ``genapi.OutOfRangeException``), PixelFormat locked while acquiring
  (``genapi.AccessException``), TriggerSoftware a command that acts only when TriggerMode is
  On with TriggerSource Software. Unknown features raise AttributeError.
- ``start()``/``stop()``; ``fetch(timeout=s)`` raises ``gentl.TimeoutException`` when no
  buffer is filled (trigger awaited, camera unplugged, every buffer still held by the
  client); ``try_fetch`` returns None instead. Free run fills a buffer on each fetch. A buffer
  must be handed back with ``queue()``: the pool has four. An unplugged camera's register
  reads raise ``gentl.IoException``.
- Images: Mono8/10/12/16 hold ``frame_number`` (times 4, 16, 256 above 8 bits, so that the
  8-bit image reads back the number) in every pixel; Bayer formats hold a mosaic of a flat scene
  of BGR ``SCENE_BGR``.
"""

from __future__ import annotations

import threading
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

SCENE_BGR = (40, 120, 220)
"""The flat colour a Bayer camera sees (blue, green, red)."""
POOL_BUFFERS = 4

MONO_SHIFT = {"Mono8": 0, "Mono10": 2, "Mono12": 4, "Mono16": 8}
BAYER_OFFSETS = {  # (row, col) of red in the 2x2 cell; blue is diagonal to it
    "BayerRG8": (0, 0),
    "BayerGR8": (0, 1),
    "BayerGB8": (1, 0),
    "BayerBG8": (1, 1),
}


# -- genicam's exceptions -----------------------------------------------------------------


class GenericException(Exception):  # noqa: N818 - the binding's names
    pass


class TimeoutException(GenericException):
    pass


class IoException(GenericException):
    pass


class OutOfRangeException(GenericException):
    pass


class InvalidArgumentException(GenericException):
    pass


class AccessException(GenericException):
    pass


# -- the cameras ---------------------------------------------------------------------------


@dataclass
class FakeGigECamera:
    """A GenICam camera. ``pixel_formats``: the PixelFormat entries it offers."""

    serial: str
    model: str = "acA1300-60gm"
    width: int = 64
    height: int = 48
    pixel_formats: tuple[str, ...] = ("Mono8", "Mono12", "Mono16")
    exposure_range_us: tuple[float, float] = (20.0, 1_000_000.0)
    gain_range_db: tuple[float, float] = (0.0, 24.0)
    plugged: bool = True
    features: dict[str, Any] = field(default_factory=dict)
    frame_number: int = 0
    acquiring: bool = False
    opened: bool = False
    filled: list[Any] = field(default_factory=list)
    held: int = 0

    def __post_init__(self) -> None:
        self.features = {
            "PixelFormat": self.pixel_formats[0],
            "ExposureTime": 5000.0,
            "ExposureAuto": "Continuous",
            "Gain": 0.0,
            "GainAuto": "Continuous",
            "TriggerSelector": "FrameStart",
            "TriggerMode": "Off",
            "TriggerSource": "Line0",
        }

    def capture(self) -> _Buffer:
        self.frame_number += 1
        fmt = self.features["PixelFormat"]
        if fmt in MONO_SHIFT:
            level = (self.frame_number % 256) << MONO_SHIFT[fmt]
            dtype = np.uint8 if fmt == "Mono8" else np.uint16
            data = np.full(self.width * self.height, level, dtype)
        else:
            mosaic = np.full((self.height, self.width), SCENE_BGR[1], np.uint8)
            r_row, r_col = BAYER_OFFSETS[fmt]
            mosaic[r_row::2, r_col::2] = SCENE_BGR[2]
            mosaic[1 - r_row :: 2, 1 - r_col :: 2] = SCENE_BGR[0]
            data = mosaic.reshape(-1)
        return _Buffer(self, _Component(data, self.width, self.height, fmt))

    def fill(self) -> None:
        """Capture one frame into a free buffer (dropped when the pool is full)."""
        if self.acquiring and self.held + len(self.filled) < POOL_BUFFERS:
            self.filled.append(self.capture())


@dataclass
class Network:
    """The cameras the fake producer sees; tests unplug, plug and trigger them here."""

    cameras: list[FakeGigECamera] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def camera(self, serial: str) -> FakeGigECamera:
        return next(c for c in self.cameras if c.serial == serial)

    def pulse(self, serial: str, line: str) -> None:
        """An electrical pulse on the camera's input ``line``."""
        with self.lock:
            cam = self.camera(serial)
            f = cam.features
            if (
                cam.plugged
                and f["TriggerMode"] == "On"
                and f["TriggerSource"] == line
                and f["TriggerSelector"] == "FrameStart"
            ):
                cam.fill()

    def queue_stale(self, serial: str, count: int) -> None:
        """``count`` free-run frames filled before anyone fetches them."""
        with self.lock:
            cam = self.camera(serial)
            for _ in range(count):
                cam.fill()

    def unplug(self, serial: str) -> None:
        with self.lock:
            cam = self.camera(serial)
            cam.plugged = False
            cam.filled.clear()

    def plug(self, serial: str) -> None:
        with self.lock:
            cam = self.camera(serial)
            cam.plugged = True
            # A camera that rebooted is not acquiring, and its stream to the old client is gone.
            cam.acquiring = False


@dataclass
class _Component:
    data: np.ndarray
    width: int
    height: int
    data_format: str


class _Payload:
    def __init__(self, component: _Component) -> None:
        self.components = [component]


class _Buffer:
    def __init__(self, camera: FakeGigECamera, component: _Component) -> None:
        self._camera = camera
        self.payload = _Payload(component)
        self._queued = False

    def queue(self) -> None:
        assert not self._queued, "a buffer is queued back once"
        self._queued = True
        self._camera.held -= 1


class _Node:
    def __init__(self, acquirer: ImageAcquirer, feature: str) -> None:
        self._acquirer, self._feature = acquirer, feature

    def _camera(self) -> FakeGigECamera:
        cam = self._acquirer.camera
        if not cam.plugged:
            raise IoException(f"reading {self._feature}: device does not respond")
        return cam

    @property
    def symbolics(self) -> tuple[str, ...]:
        cam = self._camera()
        return {
            "PixelFormat": cam.pixel_formats,
            "ExposureAuto": ("Off", "Continuous"),
            "GainAuto": ("Off", "Continuous"),
            "TriggerSelector": ("FrameStart", "AcquisitionStart"),
            "TriggerMode": ("Off", "On"),
            "TriggerSource": ("Software", "Line0", "Line1"),
        }.get(self._feature, ())

    @property
    def min(self) -> float:
        cam = self._camera()
        return (cam.exposure_range_us if self._feature == "ExposureTime" else cam.gain_range_db)[0]

    @property
    def max(self) -> float:
        cam = self._camera()
        return (cam.exposure_range_us if self._feature == "ExposureTime" else cam.gain_range_db)[1]

    @property
    def value(self) -> Any:
        return self._camera().features[self._feature]

    @value.setter
    def value(self, value: Any) -> None:
        cam = self._camera()
        if self._feature in ("ExposureTime", "Gain"):
            if not self.min <= value <= self.max:
                raise OutOfRangeException(f"{self._feature} = {value} out of range")
        elif value not in self.symbolics:
            raise InvalidArgumentException(f"{self._feature} has no entry {value!r}")
        if self._feature == "PixelFormat" and cam.acquiring:
            raise AccessException("PixelFormat is not writable while acquiring")
        cam.features[self._feature] = value

    def execute(self) -> None:
        assert self._feature == "TriggerSoftware"
        cam = self._camera()
        f = cam.features
        if f["TriggerMode"] == "On" and f["TriggerSource"] == "Software":
            cam.fill()


class _NodeMap:
    NUMBERS_AND_ENUMS = (
        "PixelFormat", "ExposureTime", "ExposureAuto", "Gain", "GainAuto",
        "TriggerSelector", "TriggerMode", "TriggerSource", "TriggerSoftware",
    )  # fmt: skip

    def __init__(self, acquirer: ImageAcquirer) -> None:
        self._acquirer = acquirer

    def __getattr__(self, feature: str) -> _Node:
        if feature not in self.NUMBERS_AND_ENUMS:
            raise AttributeError(f"'NodeMap' object has no attribute '{feature}'")
        return _Node(self._acquirer, feature)


class _RemoteDevice:
    def __init__(self, acquirer: ImageAcquirer) -> None:
        self.node_map = _NodeMap(acquirer)


class ImageAcquirer:
    def __init__(self, network: Network, camera: FakeGigECamera) -> None:
        self.network, self.camera = network, camera
        self.remote_device = _RemoteDevice(self)
        self.destroyed = False

    def start(self) -> None:
        with self.network.lock:
            if not self.camera.plugged:
                raise IoException("device does not respond")
            self.camera.acquiring = True

    def stop(self) -> None:
        with self.network.lock:
            self.camera.acquiring = False
            self.camera.filled.clear()

    def destroy(self) -> None:
        self.stop()
        self.destroyed = True
        self.camera.opened = False

    def try_fetch(self, *, timeout: float = 0) -> _Buffer | None:
        with self.network.lock:
            cam = self.camera
            # Only buffers filled before this call: free run fills the next one later.
            if self.destroyed or not cam.acquiring or not cam.plugged or not cam.filled:
                return None
            cam.held += 1
            buffer: _Buffer = cam.filled.pop(0)
            return buffer

    def fetch(self, *, timeout: float = 0) -> _Buffer:
        with self.network.lock:
            cam = self.camera
            if not self.destroyed and cam.acquiring and cam.plugged:
                if not cam.filled and cam.features["TriggerMode"] == "Off":
                    cam.fill()
                if cam.filled:
                    cam.held += 1
                    buffer: _Buffer = cam.filled.pop(0)
                    return buffer
        raise TimeoutException(f"no buffer filled within {timeout} s")


@dataclass
class _DeviceInfo:
    serial_number: str
    model: str
    vendor: str = "Fake Vision"


class Harvester:
    network: Network  # set on the fake module's class

    def __init__(self) -> None:
        self.files: list[str] = []
        self.device_info_list: list[_DeviceInfo] = []

    def add_file(self, path: str, check_existence: bool = False) -> None:
        self.files.append(path)

    def update(self) -> None:
        cameras = self.network.cameras if any(Path(f).is_file() for f in self.files) else []
        self.device_info_list = [_DeviceInfo(c.serial, c.model) for c in cameras if c.plugged]

    def create(self, search_key: dict[str, str] | None = None) -> ImageAcquirer:
        serial = (search_key or {}).get("serial_number")
        listed = [info.serial_number for info in self.device_info_list]
        if serial not in listed:
            raise ValueError(f"no device matched {search_key!r}")
        with self.network.lock:
            camera = self.network.camera(serial)
            if camera.opened:
                raise ValueError(f"device {serial} is opened by another client")
            camera.opened = True
        return ImageAcquirer(self.network, camera)

    def reset(self) -> None:
        self.files.clear()
        self.device_info_list = []


def fake_harvesters(*cameras: FakeGigECamera) -> tuple[dict[str, types.ModuleType], Network]:
    """Fresh ``harvesters``, ``harvesters.core``, ``genicam``, ``genicam.gentl`` and
    ``genicam.genapi`` module objects over a network with ``cameras``."""
    network = Network(list(cameras))
    harvesters = types.ModuleType("harvesters")
    core = types.ModuleType("harvesters.core")
    core.Harvester = type("Harvester", (Harvester,), {"network": network})  # type: ignore[attr-defined]
    harvesters.core = core  # type: ignore[attr-defined]
    genicam = types.ModuleType("genicam")
    gentl = types.ModuleType("genicam.gentl")
    genapi = types.ModuleType("genicam.genapi")
    for module, names in (
        (gentl, ("GenericException", "TimeoutException", "IoException")),
        (genapi, ("OutOfRangeException", "InvalidArgumentException", "AccessException")),
    ):
        for name in names:
            setattr(module, name, globals()[name])
    genicam.gentl = gentl  # type: ignore[attr-defined]
    genicam.genapi = genapi  # type: ignore[attr-defined]
    modules = {
        "harvesters": harvesters,
        "harvesters.core": core,
        "genicam": genicam,
        "genicam.gentl": gentl,
        "genicam.genapi": genapi,
    }
    return modules, network
