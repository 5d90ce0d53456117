"""A fake ``pyrealsense2`` module that behaves like the SDK with devices on a USB bus.

Kept for what a recording cannot show: several devices to choose from by serial, absent
devices and modes, late frames, a device busy with another pipeline, unplugging mid-stream,
framesets queued before a grab. What a recording can show (colour, depth aligned in mm by the
depth scale, intrinsics and their distortion model, timestamps) is tested against the real
SDK playing recordings (tests/vision_server/cameras/test_realsense_sdk.py).

:func:`fake_pyrealsense2` returns ``(module, bus)``: register the module as
``sys.modules["pyrealsense2"]`` (``monkeypatch.setitem``) and drive the devices through the
:class:`Bus`: plug and unplug them, stall their streams, queue stale framesets.

What it copies from librealsense 2.5x, as seen from Python:

- ``context().query_devices()`` lists the plugged devices; ``get_info(camera_info.X)``.
- ``config.enable_device/enable_stream``; ``config.can_resolve(pipeline_wrapper(p))`` is
  False for a mode the device does not offer; ``pipeline.start(config)`` raises RuntimeError
  ("No device connected", "Couldn't resolve requests", "Device or resource busy" while another
  pipeline streams from the device) and starts at most once.
- ``wait_for_frames`` before ``start`` raises RuntimeError; a stalled or unplugged device
  raises ``RuntimeError("Frame didn't arrive within N")`` (the same message for both, as
  the real SDK gives); ``poll_for_frames`` returns a falsy frameset when none is queued.
- Framesets hold a colour frame (BGR, every pixel ``frame_number % 256`` in blue, the
  device's serial tag in green) and a z16 depth frame at the depth stream's own size, in
  device units (``depth_scale`` metres each). ``align(stream.color).process`` resamples the
  depth to the colour size (nearest neighbour), as the SDK's alignment does for a flat scene
  at a constant distance.
- Intrinsics of the colour stream per mode, with a distortion model and coefficients.
"""

from __future__ import annotations

import enum
import threading
import types
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np


class camera_info(enum.Enum):  # noqa: N801 - the SDK's names
    name = 0
    serial_number = 1
    firmware_version = 2


class stream(enum.Enum):  # noqa: N801
    depth = 1
    color = 2


class format(enum.Enum):  # noqa: N801, A001
    z16 = 1
    bgr8 = 6


class distortion(enum.Enum):  # noqa: N801
    none = 0
    modified_brown_conrady = 1
    inverse_brown_conrady = 2
    ftheta = 3
    brown_conrady = 4


@dataclass
class intrinsics:  # noqa: N801
    width: int
    height: int
    ppx: float
    ppy: float
    fx: float
    fy: float
    model: distortion
    coeffs: list[float]


@dataclass
class FakeDevice:
    """A RealSense device: its serial, model, modes and what its sensors see.

    ``color_modes``/``depth_modes``: (width, height, fps) it offers. ``depth_units``: the raw
    z16 value of the flat scene it sees. ``distortion_model``/``coeffs``: of its colour stream.
    """

    serial: str
    model: str = "Intel RealSense D435"
    color_modes: tuple[tuple[int, int, int], ...] = ((640, 480, 30), (1280, 720, 30))
    depth_modes: tuple[tuple[int, int, int], ...] = ((640, 480, 30), (320, 240, 30))
    depth_scale: float = 0.001
    depth_units: int = 800
    distortion_model: distortion = distortion.inverse_brown_conrady
    coeffs: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    plugged: bool = True
    stalled: bool = False
    frame_number: int = 0
    tag: int = 7
    hold: threading.Event | None = None
    """When set to an Event, wait_for_frames blocks until it is set (a slow exposure)."""
    waiting: threading.Event = field(default_factory=threading.Event)
    """Set while a wait_for_frames is blocked on ``hold``."""

    def color_intrinsics(self, width: int, height: int) -> intrinsics:
        scale = width / 640
        return intrinsics(
            width, height, 321.5 * scale, 238.25 * scale, 615.0 * scale, 616.0 * scale,
            self.distortion_model, list(self.coeffs),
        )  # fmt: skip

    def get_info(self, what: camera_info) -> str:
        if not self.plugged:
            raise RuntimeError("device disconnected")
        if what is camera_info.serial_number:
            return self.serial
        if what is camera_info.name:
            return self.model
        return "5.16.0.1"

    def first_depth_sensor(self) -> _DepthSensor:
        return _DepthSensor(self)


@dataclass
class _DepthSensor:
    device: FakeDevice

    def get_depth_scale(self) -> float:
        return self.device.depth_scale


@dataclass
class Bus:
    """The USB bus the fake context sees; tests plug, unplug and stall devices here."""

    devices: list[FakeDevice] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    pipelines: list[pipeline] = field(default_factory=list)

    def add(self, device: FakeDevice) -> FakeDevice:
        self.devices.append(device)
        return device

    def device(self, serial: str) -> FakeDevice:
        return next(d for d in self.devices if d.serial == serial)

    def queue_stale(self, serial: str, count: int) -> None:
        """``count`` framesets captured now and queued in the device's running pipeline."""
        with self.lock:
            for p in self.pipelines:
                if p.started and p.device is not None and p.device.serial == serial:
                    for _ in range(count):
                        p.queue.append(p.capture())


class _Frame:
    def __init__(self, data: np.ndarray | None, number: int) -> None:
        self._data = data
        self._number = number

    def __bool__(self) -> bool:
        return self._data is not None

    def get_data(self) -> np.ndarray:
        assert self._data is not None
        return self._data

    def get_frame_number(self) -> int:
        return self._number


class composite_frame:  # noqa: N801
    def __init__(self, color: _Frame | None, depth: _Frame | None, number: int) -> None:
        self._color, self._depth, self._number = color, depth, number

    def __bool__(self) -> bool:
        return self._color is not None or self._depth is not None

    def get_color_frame(self) -> _Frame:
        return self._color or _Frame(None, 0)

    def get_depth_frame(self) -> _Frame:
        return self._depth or _Frame(None, 0)

    def get_frame_number(self) -> int:
        return self._number


class align:  # noqa: N801
    def __init__(self, to: stream) -> None:
        assert to is stream.color, "the backend aligns depth to colour"
        self.to = to

    def process(self, frames: composite_frame) -> composite_frame:
        color = frames.get_color_frame()
        depth = frames.get_depth_frame()
        if not color or not depth:
            return frames
        height, width = color.get_data().shape[:2]
        resized = cv2.resize(depth.get_data(), (width, height), interpolation=cv2.INTER_NEAREST)
        return composite_frame(color, _Frame(resized, depth.get_frame_number()), frames._number)


class config:  # noqa: N801
    def __init__(self) -> None:
        self.serial: str | None = None
        self.streams: dict[stream, tuple[int, int, format, int]] = {}

    def enable_device(self, serial: str) -> None:
        self.serial = serial

    def enable_stream(self, kind: stream, width: int, height: int, fmt: format, fps: int) -> None:
        self.streams[kind] = (width, height, fmt, fps)

    def can_resolve(self, wrapper: pipeline_wrapper) -> bool:
        return wrapper.pipeline.resolve(self) is not None


class pipeline_wrapper:  # noqa: N801
    def __init__(self, p: pipeline) -> None:
        self.pipeline = p


class _VideoProfile:
    def __init__(self, k: intrinsics) -> None:
        self._k = k

    def as_video_stream_profile(self) -> _VideoProfile:
        return self

    def get_intrinsics(self) -> intrinsics:
        return self._k


class pipeline_profile:  # noqa: N801
    def __init__(self, device: FakeDevice, color: tuple[int, int]) -> None:
        self._device, self._color = device, color

    def get_device(self) -> FakeDevice:
        return self._device

    def get_stream(self, kind: stream) -> _VideoProfile:
        assert kind is stream.color
        return _VideoProfile(self._device.color_intrinsics(*self._color))


class context:  # noqa: N801
    bus: Bus  # set on the fake module's class

    def query_devices(self) -> list[FakeDevice]:
        return [d for d in self.bus.devices if d.plugged]


class pipeline:  # noqa: N801
    def __init__(self, ctx: context | None = None) -> None:
        self.ctx = ctx or context()
        self.started = False
        self.device: FakeDevice | None = None
        self.streams: dict[stream, tuple[int, int, format, int]] = {}
        self.queue: list[composite_frame] = []

    def resolve(self, cfg: config) -> FakeDevice | None:
        candidates = [
            d for d in self.ctx.query_devices() if cfg.serial is None or d.serial == cfg.serial
        ]
        for device in candidates:
            ok = True
            for kind, (width, height, fmt, fps) in cfg.streams.items():
                modes = device.color_modes if kind is stream.color else device.depth_modes
                wanted_fmt = format.bgr8 if kind is stream.color else format.z16
                ok = ok and (width, height, fps) in modes and fmt is wanted_fmt
            if ok:
                return device
        return None

    def start(self, cfg: config) -> pipeline_profile:
        if self.started:
            raise RuntimeError("start() cannot be called before stop()")
        if not self.ctx.query_devices():
            raise RuntimeError("No device connected")
        device = self.resolve(cfg)
        if device is None:
            raise RuntimeError("Couldn't resolve requests")
        with self.ctx.bus.lock:
            if any(p.device is device for p in self.ctx.bus.pipelines):
                raise RuntimeError(
                    "xioctl(VIDIOC_S_FMT) failed, errno=16 Last Error: Device or resource busy"
                )
        self.started, self.device, self.streams = True, device, dict(cfg.streams)
        with self.ctx.bus.lock:
            self.ctx.bus.pipelines.append(self)
        width, height = cfg.streams[stream.color][:2]
        return pipeline_profile(device, (width, height))

    def stop(self) -> None:
        if not self.started:
            raise RuntimeError("stop() cannot be called before start()")
        self.started = False
        self.queue.clear()
        with self.ctx.bus.lock:
            self.ctx.bus.pipelines.remove(self)

    def capture(self) -> composite_frame:
        """The device's next frameset (call with the bus lock held)."""
        device = self.device
        assert device is not None
        device.frame_number += 1
        number = device.frame_number
        width, height = self.streams[stream.color][:2]
        color = np.zeros((height, width, 3), np.uint8)
        color[:, :, 0] = number % 256
        color[:, :, 1] = device.tag
        depth = None
        if stream.depth in self.streams:
            dw, dh = self.streams[stream.depth][:2]
            depth = _Frame(np.full((dh, dw), device.depth_units, np.uint16), number)
        return composite_frame(_Frame(color, number), depth, number)

    def poll_for_frames(self) -> composite_frame:
        if not self.started:
            raise RuntimeError("poll_for_frames cannot be called before start()")
        with self.ctx.bus.lock:
            if self.queue:
                return self.queue.pop(0)
        return composite_frame(None, None, 0)

    def wait_for_frames(self, timeout_ms: int = 5000) -> composite_frame:
        if not self.started:
            raise RuntimeError("wait_for_frames cannot be called before start()")
        hold = self.device.hold if self.device is not None else None
        if hold is not None:
            self.device.waiting.set()  # type: ignore[union-attr]
            hold.wait()
        with self.ctx.bus.lock:
            device = self.device
            assert device is not None
            if not device.plugged or device.stalled:
                self.queue.clear()
                raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
            if self.queue:
                return self.queue.pop(0)
            return self.capture()


def fake_pyrealsense2(*devices: FakeDevice) -> tuple[types.ModuleType, Bus]:
    """A fresh ``pyrealsense2`` module object over a bus with ``devices`` plugged in."""
    bus = Bus(list(devices))
    module = types.ModuleType("pyrealsense2")
    ctx_class = type("context", (context,), {"bus": bus})
    pipe_class = type("pipeline", (pipeline,), {"__init__": _pipeline_init(ctx_class)})
    names: dict[str, Any] = {
        "camera_info": camera_info,
        "stream": stream,
        "format": format,
        "distortion": distortion,
        "intrinsics": intrinsics,
        "context": ctx_class,
        "pipeline": pipe_class,
        "pipeline_wrapper": pipeline_wrapper,
        "pipeline_profile": pipeline_profile,
        "config": config,
        "align": align,
        "composite_frame": composite_frame,
    }
    for name, value in names.items():
        setattr(module, name, value)
    return module, bus


def _pipeline_init(ctx_class: type[context]) -> Any:
    def init(self: pipeline, ctx: context | None = None) -> None:
        pipeline.__init__(self, ctx or ctx_class())

    return init
