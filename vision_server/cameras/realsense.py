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

Playback (``playback: FILE``): the camera plays a RealSense recording (the SDK's own file, see
:mod:`.realsense_recording`) through the same SDK: ``rs.config().enable_device_from_file``,
the pipeline, ``rs.align`` to colour, the depth scale of the recording's depth sensor and the
colour intrinsics stored in the recording. Decisions, each for what the SDK (2.59.1) did:

- Not in real time (``playback.set_real_time(False)``): an integrator replaying for tuning
  wants every frame in order, so each grab takes the recording's next frame however long the
  inspections take; a real-time playback drops the frames nobody took in time. It is set on
  the device the pipeline starts (the configuration's last ``resolve``) before it starts, and
  the playback is paused until every stream runs (else the first frames were lost now and
  then); the SDK's ``resume`` then blocks for 10 s now and then, which the connect waits out.
- The pipeline hands over a frameset whenever a frame of either stream arrives, with the
  latest frame of the other: a grab takes the next frameset whose colour frame it has not
  taken and whose depth frame is of the same moment (timestamps within half a frame period);
  colour frames the SDK lost or never paired with depth are counted (``frames_lost``).
- Frame timestamps are the recording's (the SDK's milliseconds as seconds) when they are
  epoch time (``system_time``/``global_time`` domain, as the recorder writes them).
- Depth already registered to colour (the same intrinsics, an identity extrinsic) is not put
  through ``rs.align``, which is not exactly the identity there (see :func:`_registered`);
  a depth stream whose pixel count is not a multiple of 8 is refused, since ``rs.align``
  writes past its buffers on it.
- The end of the recording: every later grab raises CAMERA_UNAVAILABLE "the recording FILE
  ended after N frames" and the camera stays connected and *ended* (no reconnect, which would
  play it again). It does not loop: ``repeat_playback`` dropped frames at the turn, and
  starting a played recording again hung now and then.
- A missing file, a file the SDK cannot read as a recording, no colour stream, no depth stream
  with ``depth``, or streams of another size than configured: down, with that cause.

Live devices are not tried (no device was at hand); playback is tested with recordings written
by ``rs.software_device`` + ``rs.recorder``: see README.md ("Real devices").
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..process import decoder_limits
from .base import CameraFrame, public_path
from .clock import Clock
from .device import DeviceCamera, DeviceError, FrameTimeout, import_sdk
from .settings import Intrinsics, RealSenseCameraSettings

__all__ = ["RealSenseCamera", "depth_to_mm"]

_MAX_STALE_FRAMESETS = 16
"""Framesets dropped at most before a grab waits for a fresh one (the SDK queues a few)."""

_PLAYBACK_SLICE_S = 0.1
"""A playback grab waits for the SDK in slices this long, looking in between whether the
recording has ended (so that the end is answered at once, not after the grab's timeout)."""

_END_GRACE_S = 1.0
"""Once the SDK says the recording stopped, how long a grab still waits for frames on their
way through the pipeline before it declares the end."""


class RecordingEnded(FrameTimeout):
    """The recording has no more frames: every grab says so, the camera is not
    down (connecting again would play the recording again)."""


def depth_to_mm(raw: NDArray[np.uint16], depth_scale_m: float) -> NDArray[np.uint16]:
    """Depth in device units (``raw``, 0 = none) -> uint16 millimetres, rounded, clipped at
    65535 mm. ``depth_scale_m``: metres per device unit."""
    factor = depth_scale_m * 1000.0
    if abs(factor - 1.0) < 1e-9:
        return np.array(raw, dtype=np.uint16)
    scaled = np.rint(raw.astype(np.float64) * factor)
    return np.clip(scaled, 0, 65535).astype(np.uint16)


def _registered(depth: Any, color: Any) -> bool:
    """Whether a recording's depth stream is already registered to its colour stream: the
    same intrinsics and an identity extrinsic between them (as :class:`RealSenseRecorder`
    writes depth that has the colour's intrinsics). ``rs.align`` is the identity there, but
    not exactly: rounding in its reprojection loses about 1 % of the pixels and moves another
    0.2 % to a neighbour's depth (measured on the simulated cell's 640x480 view)."""
    k_depth = depth.as_video_stream_profile().get_intrinsics()
    k_color = color.get_intrinsics()
    fields = ("width", "height", "fx", "fy", "ppx", "ppy", "model")
    if any(getattr(k_depth, f) != getattr(k_color, f) for f in fields):
        return False
    if list(k_depth.coeffs) != list(k_color.coeffs):
        return False
    extrinsics = depth.get_extrinsics_to(color)
    identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    return list(extrinsics.rotation) == identity and not any(extrinsics.translation)


class RealSenseCamera(DeviceCamera):
    """An Intel RealSense camera (see the module)."""

    source = "realsense"

    def __init__(
        self,
        name: str,
        settings: RealSenseCameraSettings,
        *,
        base_dir: Path | None = None,
        clock: Clock | None = None,
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
        self.playback_path: Path | None = None
        """The recording played (absolute when ``base_dir`` was given), or None: a device."""
        if settings.playback is not None:
            path = settings.playback.expanduser()
            if not path.is_absolute() and base_dir is not None:
                path = base_dir / path
            self.playback_path = path
            self.hide_path(path, public_path(settings.playback))
        self._playback: Any = None
        self._half_period_ms = 0.0
        self._taken: tuple[int, float] | None = None  # the last colour frame: (number, ms)
        self._taken_count = 0  # frames taken from the recording since it started
        self._skipped = 0  # framesets passed over: their colour had no depth of its moment
        self._lost = 0  # colour frames of the recording the SDK never handed over with depth
        self._ended: str | None = None
        self._sdk_times: dict[int, float] = {}  # frame index -> the SDK's timestamp (s)
        self._color_format: Any = None

    # -- connect ---------------------------------------------------------------------------

    def _connect(self) -> None:
        rs = self._rs = import_sdk("pyrealsense2", extra="realsense")
        if self.playback_path is not None:
            self._connect_playback(rs, self.playback_path)
            return
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

    def _connect_playback(self, rs: ModuleType, path: Path) -> None:
        """Start playing the recording ``path`` through the SDK's pipeline (see the module)."""
        s = self.settings
        if not path.is_file():
            what = "is not a file" if path.exists() else "does not exist"
            raise DeviceError(f"the recording {path} {what}")
        pipeline = rs.pipeline()
        config = rs.config()
        try:
            config.enable_device_from_file(str(path), repeat_playback=False)
            # Resolved with no stream asked for: every recorded stream, to see what is there.
            recorded = config.resolve(rs.pipeline_wrapper(pipeline))
        except RuntimeError as exc:
            raise DeviceError(
                f"the file {path} is not a RealSense recording the SDK can read: {exc}"
            ) from exc
        streams: dict[Any, Any] = {}
        for stream in recorded.get_streams():
            streams.setdefault(stream.stream_type(), stream)
        names = ", ".join(sorted(str(kind).split(".")[-1] for kind in streams)) or "none"
        color = streams.get(rs.stream.color)
        if color is None:
            raise DeviceError(f"the recording {path} has no colour stream (it has: {names})")
        depth = streams.get(rs.stream.depth)
        if s.depth and depth is None:
            raise DeviceError(
                f"the recording {path} has no depth stream (it has: {names}); "
                "set depth: false to play its colour alone"
            )
        if color.format() not in (rs.format.bgr8, rs.format.rgb8):
            raise DeviceError(
                f"the recording {path}'s colour stream is {color.format()}, not bgr8 or rgb8"
            )
        sizes = []
        if s.width is not None and s.height is not None:
            sizes.append(("colour", color, (s.width, s.height), "width/height"))
        if s.depth and s.depth_width is not None and s.depth_height is not None:
            sizes.append(("depth", depth, (s.depth_width, s.depth_height), "depth_width/height"))
        for what, stream, wanted, keys in sizes:
            video = stream.as_video_stream_profile()
            size = (int(video.width()), int(video.height()))
            if size != wanted:
                raise DeviceError(
                    f"the recording {path}'s {what} stream is {size[0]}x{size[1]} but the "
                    f"camera is set to {wanted[0]}x{wanted[1]} ({keys})"
                )
        # The server's image size bound holds for a recording as for an image a client sends:
        # a stream beyond it is refused before a frame of it is decoded.
        limit = decoder_limits.loaded_limit() or decoder_limits.DEFAULT_MAX_IMAGE_PIXELS
        for what, stream in (("colour", color), ("depth", depth)):
            if stream is None or (what == "depth" and not s.depth):
                continue
            video = stream.as_video_stream_profile()
            pixels = int(video.width()) * int(video.height())
            if pixels > limit:
                raise DeviceError(
                    f"the recording {path}'s {what} stream is {video.width()}x{video.height()}, "
                    f"more than the server's {limit} pixels (max_image_pixels)"
                )
        config.enable_stream(rs.stream.color)
        if s.depth:
            config.enable_stream(rs.stream.depth)
        try:
            # As fast as read, not in real time: the reader waits until a frame is taken, so
            # every grab gets the next frame, none dropped however slow the inspections. Set
            # before the start on the device the start will use: the configuration's last
            # resolve (a changed configuration resolves to a new device, which would start
            # in real time and drop frames before it could be told otherwise).
            resolved = config.resolve(rs.pipeline_wrapper(pipeline)).get_device().as_playback()
            resolved.set_real_time(False)
            # Paused until the pipeline has started every stream: else the first frames were
            # lost or paired across streams now and then (8 of 300 starts on a loaded
            # machine, 0 of 300 paused). resume() then blocks 10 s now and then (3 of 90).
            resolved.pause()
            profile = pipeline.start(config)
            profile.get_device().as_playback().resume()
            self._pipeline = pipeline
            device = profile.get_device()
            playback = self._playback = device.as_playback()
            if playback.is_real_time():
                raise DeviceError(
                    f"the SDK started the recording {path} in real time, where it drops "
                    "frames that are not taken at once"
                )
            info: dict[str, Any] = {"playback": public_path(s.playback or path)}
            fields = (("model", rs.camera_info.name), ("serial", rs.camera_info.serial_number))
            for key, field in fields:
                if device.supports(field):
                    info[key] = str(device.get_info(field))
            video = profile.get_stream(rs.stream.color).as_video_stream_profile()
            if s.depth:
                self._depth_scale_m = float(device.first_depth_sensor().get_depth_scale())
                info["depth_scale_m"] = self._depth_scale_m
                depth_stream = profile.get_stream(rs.stream.depth).as_video_stream_profile()
                registered = _registered(depth_stream, video)
                pixels = int(depth_stream.width()) * int(depth_stream.height())
                if not registered and pixels % 8:
                    # Measured with 2.59.1: align then writes past its buffers and the
                    # process dies (every RealSense depth mode has a multiple of 8 pixels).
                    raise DeviceError(
                        f"the recording {path}'s depth stream is {depth_stream.width()}x"
                        f"{depth_stream.height()}, whose pixel count is not a multiple of 8: "
                        "the SDK's align corrupts memory on such frames"
                    )
                self._align = None if registered else rs.align(rs.stream.color)
                info["align"] = not registered
            self._half_period_ms = 500.0 / max(float(video.fps()), 1.0)
            self._color_format = video.format()
            intrinsics = self._intrinsics_of(rs, video.get_intrinsics())
        except RuntimeError as exc:
            raise DeviceError(f"playing the recording {path} failed: {exc}") from exc
        self._serial = info.get("serial")
        self._device_info = info
        self._taken, self._taken_count, self._skipped, self._ended = None, 0, 0, None
        self._lost = 0
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

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        frame = super().grab(timeout_s=timeout_s, newer_than=newer_than)
        sdk_time = self._sdk_times.pop(frame.index, None)
        if sdk_time is None:
            return frame
        return dataclasses.replace(frame, timestamp=sdk_time)

    def _read(self, timeout_s: float) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
        if self._playback is not None:
            return self._read_playback(timeout_s)
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

    def _read_playback(
        self, timeout_s: float
    ) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
        """The recording's next frame: the next frameset whose colour frame was not taken
        before and, with depth, whose depth frame is of the same moment (see the module)."""
        rs = self._rs
        assert rs is not None
        if self._ended is not None:
            raise RecordingEnded(self._ended)
        # Real time: the SDK's waits know no other clock.
        deadline = time.monotonic() + timeout_s
        stopped_at: float | None = None
        while True:
            now = time.monotonic()
            if stopped_at is None and self._playback.current_status() == rs.playback_status.stopped:
                stopped_at = now
            if stopped_at is not None and now - stopped_at >= _END_GRACE_S:
                lost = f", {self._lost} more lost by the SDK" if self._lost else ""
                self._ended = (
                    f"the recording {self.playback_path} ended after {self._taken_count} "
                    f"frames{lost}"
                )
                self._device_info["ended"] = True
                raise RecordingEnded(self._ended)
            if now >= deadline:
                raise FrameTimeout(
                    f"no frame from the recording {self.playback_path} within {timeout_s:.3g} s"
                )
            wait_s = min(deadline - now, _PLAYBACK_SLICE_S)
            try:
                frames = self._pipeline.wait_for_frames(max(1, round(wait_s * 1000)))
            except RuntimeError:
                continue  # nothing within this slice: look at the recording's state again
            stopped_at = None  # frames still come
            taken = self._take(frames)
            if taken is not None:
                return taken

    def _take(self, frames: Any) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None] | None:
        """A frameset's (colour, depth mm), or None when it is not a new frame.

        The SDK's pipeline hands over a frameset whenever a frame of any stream arrives,
        with the latest frame of each other stream: a frameset whose colour frame was taken
        already, or whose depth is from another moment than its colour (more than half a
        frame period apart), is passed over.
        """
        rs = self._rs
        assert rs is not None
        color_frame = frames.get_color_frame()
        if not color_frame:
            return None
        number, stamp = int(color_frame.get_frame_number()), float(color_frame.get_timestamp())
        if self._taken == (number, stamp):
            return None
        if self.settings.depth:
            depth_frame = frames.get_depth_frame()
            if not depth_frame or abs(depth_frame.get_timestamp() - stamp) > self._half_period_ms:
                self._skipped += 1
                self._device_info["skipped_framesets"] = self._skipped
                return None
            if self._align is not None:
                frames = self._align.process(frames)
                color_frame = frames.get_color_frame()
                depth_frame = frames.get_depth_frame()
            raw = np.asanyarray(depth_frame.get_data())
            if raw.dtype != np.uint16:
                raise DeviceError(f"depth frames are {raw.dtype}, expected z16 (uint16)")
            depth: NDArray[np.uint16] | None = depth_to_mm(raw, self._depth_scale_m)
        else:
            depth = None
        color = np.array(np.asanyarray(color_frame.get_data()), dtype=np.uint8)
        if self._color_format == rs.format.rgb8:
            color = np.ascontiguousarray(color[:, :, ::-1])
        if self._taken is not None and number > self._taken[0] + 1:
            # Frame numbers the recording has but the SDK did not deliver (with depth).
            self._lost += number - self._taken[0] - 1
            self._device_info["frames_lost"] = self._lost
        self._taken = (number, stamp)
        self._taken_count += 1
        domain = color_frame.get_frame_timestamp_domain()
        if domain in (rs.timestamp_domain.system_time, rs.timestamp_domain.global_time):
            self._sdk_times[self._next_index] = stamp / 1000.0
        return color, depth

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

    def status(self) -> dict[str, Any]:
        status = super().status()
        if self._ended is not None and status["state"] == "up":
            status["state"] = "ended"
        return status

    def _disconnect(self) -> None:
        pipeline, self._pipeline = self._pipeline, None
        self._align = None
        self._playback = None
        if pipeline is not None:
            with contextlib.suppress(RuntimeError):  # already stopped, or the device is gone
                pipeline.stop()
