"""The ``aravis`` source: a GigE Vision or USB3 Vision camera through Aravis.

Aravis is the open-source GenICam stack (GVCP/GVSP for GigE Vision, U3V for USB3 Vision): it
reads the device's own GenICam XML and needs no vendor GenTL producer. Python reaches Debian's
``libaravis-0.8`` through GObject introspection (PyGObject, the ``aravis`` extra, plus the
``gir1.2-aravis-0.8`` package), imported when the camera first connects. The ``genicam``
source (harvesters) stays for cameras whose vendor ships only a GenTL producer.

Connecting: the device is opened by ``address`` directly, or found by ``serial`` or
``device_id`` among the devices Aravis discovers (about one second of discovery). GigE Vision
grants control of a device to one application at a time: a device another application
controls is refused with that cause (and tried again every ``reconnect_interval_s``, so a
second server takes over when the first lets go). Then PixelFormat, region, ExposureTime,
Gain, AcquisitionFrameRate, the trigger and the GVSP packet size are set, each checked first
against the device's own range or entries, so that a refusal names the configuration key,
the feature and the range; then acquisition starts with ``buffers`` frames queued.

A grab, by ``trigger``:

- ``free_run``: drops the frames the device delivered before the grab, takes the next one.
- ``software``: drops them, fires TriggerSoftware, takes the frame it triggered; a frame
  that arrives incomplete (packets lost beyond resends) is triggered again, within the
  grab's timeout.
- ``hardware``: takes the next frame triggered on ``trigger_source``, in trigger order; an
  incomplete one is an error (the PLC's trigger was lost), not silently replaced.

A device that stops answering (the heartbeat lost, or no frame and no register answer) is
disconnected and reconnected later (:mod:`vision_server.cameras.device`). The stream's
statistics (frames completed and failed, packets received, missing and resent) add up across
reconnects and are in ``status()["stream"]``. Without ``region`` the camera takes the whole
sensor; without ``exposure_us``, ``gain_db`` or ``frame_rate_hz`` it keeps the device's current
value, which may be one another application (or this server before a reload) left. The
device reports no intrinsics: give them in the configuration for measuring inspections.

Tried against Aravis' own GigE Vision emulator (``arv-fake-gv-camera-0.8``), not a physical
camera: see README.md ("Real devices").
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .clock import Clock
from .device import DeviceCamera, DeviceError, FrameTimeout, import_sdk
from .pixels import convert_pixels
from .settings import AravisCameraSettings

__all__ = ["AravisCamera", "STREAM_COUNTERS", "aravis_module"]

PIXEL_FORMAT_NAMES = {
    0x01080001: "Mono8",
    0x01100003: "Mono10",
    0x01100005: "Mono12",
    0x01100007: "Mono16",
    0x01080008: "BayerGR8",
    0x01080009: "BayerRG8",
    0x0108000A: "BayerGB8",
    0x0108000B: "BayerBG8",
    0x02180014: "RGB8",
    0x02180015: "BGR8",
}
"""GenICam PFNC codes (what a buffer carries) -> their names."""

STREAM_COUNTERS = {
    "frames_completed": "n_completed_buffers",
    "frames_failed": "n_failures",
    "underruns": "n_underruns",
    "packets_received": "n_received_packets",
    "packets_missing": "n_missing_packets",
    "packets_resent": "n_resent_packets",
    "resend_requests": "n_resend_requests",
}
"""``status()["stream"]`` keys -> Aravis' stream statistics (a USB3 Vision stream has no
packets: those read 0). ``underruns`` counts data that arrived while every buffer was full:
in free run it grows between grabs (nobody takes frames then), and is no fault."""

_REFIRE_AFTER_S = 1.0
"""A software trigger with no frame after this long is fired again (within the grab)."""
_POP_SLICE_US = 200_000
"""A wait for a buffer is cut into slices this long, so a lost heartbeat ends it early."""


def aravis_module() -> Any:
    """Aravis' introspected module (``gi.repository.Aravis``), or :class:`DeviceError` naming
    what to install."""
    gi = import_sdk("gi", extra="aravis")
    try:
        gi.require_version("Aravis", "0.8")
    except ValueError as exc:
        raise DeviceError(
            f"Aravis 0.8 is not installed (Debian: apt-get install gir1.2-aravis-0.8): {exc}"
        ) from exc
    repository = import_sdk("gi.repository.Aravis", extra="aravis")
    return repository


def _error_text(exc: BaseException) -> str:
    """A GLib error's message without its quark and code."""
    message = getattr(exc, "message", None)
    return str(message) if message else str(exc)


class AravisCamera(DeviceCamera):
    """A GenICam camera through Aravis (see the module)."""

    source = "aravis"

    @property
    def triggered(self) -> bool:
        """A software or hardware trigger: the live view must not fire or take one."""
        return self.settings.trigger != "free_run"

    def __init__(
        self, name: str, settings: AravisCameraSettings, *, clock: Clock | None = None
    ) -> None:
        super().__init__(
            name,
            intrinsics=settings.intrinsics,
            has_depth=False,
            reconnect_interval_s=settings.reconnect_interval_s,
            clock=clock,
        )
        self.settings = settings
        self._arv: Any = None
        self._camera: Any = None
        self._stream: Any = None
        self._control_lost = threading.Event()
        self._last_frame: dict[str, Any] | None = None
        """The device's own account of the newest frame: its frame ID (GVSP block ID),
        timestamp (device ticks, ns on most devices) and region [x, y, width, height]."""
        self._totals = dict.fromkeys(STREAM_COUNTERS, 0)
        """Stream statistics of the streams before the current one (reconnects)."""

    # -- connect ---------------------------------------------------------------------------

    def _connect(self) -> None:
        arv = self._arv = aravis_module()
        self._control_lost.clear()
        device_id = self._find_device(arv)
        try:
            camera = self._camera = arv.Camera.new(device_id)
        except Exception as exc:  # noqa: BLE001 - GLib.GError: unreachable, refused ...
            raise DeviceError(
                f"opening {self._describe_wanted()} failed: {_error_text(exc)}"
            ) from exc
        device = camera.get_device()
        serial = str(camera.get_device_serial_number() or "?")
        self._device_info = {
            "serial": serial,
            "model": str(camera.get_model_name() or "?"),
            "vendor": str(camera.get_vendor_name() or "?"),
            "device_id": str(camera.get_device_id() or "?"),
            "address": device_id if self.settings.address else self._address_of(arv, serial),
            "protocol": "GigE Vision" if camera.is_gv_device() else "USB3 Vision",
        }
        if camera.is_gv_device() and not device.is_controller():
            raise DeviceError(
                f"{self._who()} is controlled by another application (another server, or "
                "another camera of this configuration: GigE Vision grants control to one at "
                "a time)"
            )
        with contextlib.suppress(Exception):
            device.connect("control-lost", self._on_control_lost)
        self._configure(camera)
        try:
            stream = camera.create_stream(None, None)
        except Exception as exc:  # noqa: BLE001
            raise DeviceError(
                f"opening a stream from {self._who()} failed: {_error_text(exc)}"
            ) from exc
        if camera.is_gv_device():
            # A socket buffer sized to a whole frame: the default one overflows at a few tens
            # of frames a second on a fast link, and the frames arrive incomplete.
            stream.set_property("socket-buffer", arv.GvStreamSocketBuffer.AUTO)
            resend = arv.GvStreamPacketResend
            stream.set_property(
                "packet-resend", resend.ALWAYS if self.settings.packet_resend else resend.NEVER
            )
        try:
            payload = int(camera.get_payload())
            for _ in range(self.settings.buffers):
                stream.push_buffer(arv.Buffer.new_allocate(payload))
            with self._state_lock:
                self._stream = stream
            camera.start_acquisition()
        except Exception as exc:  # noqa: BLE001
            raise DeviceError(
                f"starting acquisition on {self._who()} failed: {_error_text(exc)}"
            ) from exc

    def _describe_wanted(self) -> str:
        s = self.settings
        if s.address is not None:
            return f"the device at {s.address}"
        if s.serial is not None:
            return f"the device with serial {s.serial}"
        if s.device_id is not None:
            return f"the device {s.device_id}"
        return "the only Aravis device"

    def _who(self) -> str:
        info = self._device_info
        return f"{info.get('model', '?')} {info.get('serial', '?')} at {info.get('address', '?')}"

    def _find_device(self, arv: Any) -> str:
        """What ``Camera.new`` opens: the configured address as it is, or the ID of the
        device discovered with the configured serial or ID (or the only one)."""
        s = self.settings
        if s.address is not None:
            return s.address
        arv.update_device_list()
        found = [
            {
                "id": str(arv.get_device_id(i)),
                "serial": str(arv.get_device_serial_nbr(i)),
                "address": str(arv.get_device_address(i)),
            }
            for i in range(arv.get_n_devices())
        ]
        listed = ", ".join(f"{d['id']} (serial {d['serial']}, {d['address']})" for d in found)
        visible = f"visible: {listed or 'none'}"
        if s.serial is not None:
            match = [d for d in found if d["serial"] == s.serial]
        elif s.device_id is not None:
            match = [d for d in found if d["id"] == s.device_id]
        else:
            if len(found) != 1:
                what = "no Aravis device is visible" if not found else "several are visible"
                raise DeviceError(f"{what} ({visible}); set serial, device_id or address")
            match = found
        if not match:
            raise DeviceError(f"{self._describe_wanted()} is not visible ({visible})")
        return match[0]["id"]

    @staticmethod
    def _address_of(arv: Any, serial: str) -> str:
        for i in range(arv.get_n_devices()):
            if str(arv.get_device_serial_nbr(i)) == serial:
                return str(arv.get_device_address(i))
        return "?"

    def _on_control_lost(self, *_: Any) -> None:
        # Called on Aravis' heartbeat thread: only a flag, the grabbing thread acts on it.
        self._control_lost.set()

    # -- settings --------------------------------------------------------------------------

    def _check_range(
        self, key: str, feature: str, value: float, bounds: Any, unit: str = ""
    ) -> None:
        low, high = float(bounds[0]), float(bounds[1])
        if not low <= value <= high:
            raise DeviceError(
                f"{key} {value:g} is outside the device's {feature} range [{low:g}, {high:g}]{unit}"
            )

    def _apply(self, key: str, feature: str, action: Callable[[], Any]) -> None:
        try:
            action()
        except DeviceError:
            raise
        except Exception as exc:  # noqa: BLE001 - GLib.GError from the device or GenICam
            raise DeviceError(f"{key}: the device refused {feature}: {_error_text(exc)}") from exc

    def _configure(self, camera: Any) -> None:
        s = self.settings
        arv = self._arv
        formats = [str(f) for f in camera.dup_available_pixel_formats_as_strings() or []]
        if s.pixel_format not in formats:
            raise DeviceError(
                f"pixel_format: the device's PixelFormat offers {formats}, not {s.pixel_format!r}"
            )
        self._apply(
            "pixel_format",
            "PixelFormat",
            lambda: camera.set_pixel_format_from_string(s.pixel_format),
        )
        # No region configured: the whole sensor, not whatever region the device was left
        # with by the last application (or this server's configuration before a reload).
        self._set_region(camera, s.region or self._whole_sensor(camera))
        if s.exposure_us is not None:
            if camera.is_exposure_auto_available():
                self._apply(
                    "exposure_us",
                    "ExposureAuto",
                    lambda: camera.set_exposure_time_auto(arv.Auto.OFF),
                )
            bounds = camera.get_exposure_time_bounds()
            self._check_range("exposure_us", "ExposureTime", s.exposure_us, bounds, " us")
            self._apply(
                "exposure_us", "ExposureTime", lambda: camera.set_exposure_time(s.exposure_us)
            )
        if s.gain_db is not None:
            if camera.is_gain_auto_available():
                self._apply("gain_db", "GainAuto", lambda: camera.set_gain_auto(arv.Auto.OFF))
            self._check_range("gain_db", "Gain", s.gain_db, camera.get_gain_bounds(), " dB")
            self._apply("gain_db", "Gain", lambda: camera.set_gain(s.gain_db))
        # The rate before the trigger: Aravis sets it with the frame trigger off.
        if s.frame_rate_hz is not None:
            if not camera.is_frame_rate_available():
                raise DeviceError("frame_rate_hz: the device has no AcquisitionFrameRate feature")
            bounds = camera.get_frame_rate_bounds()
            self._check_range("frame_rate_hz", "AcquisitionFrameRate", s.frame_rate_hz, bounds)
            self._apply(
                "frame_rate_hz",
                "AcquisitionFrameRate",
                lambda: camera.set_frame_rate(s.frame_rate_hz),
            )
        self._set_trigger(camera)
        if camera.is_gv_device():
            self._set_packet_size(camera)

    @staticmethod
    def _whole_sensor(camera: Any) -> tuple[int, int, int, int]:
        """[0, 0, width, height]: the largest image the device gives (its sensor, or the
        largest Width and Height it allows at the current binning)."""
        width = int(camera.get_width_bounds()[1])
        height = int(camera.get_height_bounds()[1])
        return (0, 0, width, height)

    def _set_region(self, camera: Any, region: tuple[int, int, int, int]) -> None:
        x, y, width, height = region
        for key, feature, value, bounds in (
            ("region width", "Width", width, camera.get_width_bounds()),
            ("region height", "Height", height, camera.get_height_bounds()),
        ):
            self._check_range(key, feature, value, bounds, " px")
        sensor = camera.get_sensor_size()
        sensor_w, sensor_h = int(sensor[0]), int(sensor[1])
        if x + width > sensor_w or y + height > sensor_h:
            raise DeviceError(
                f"region [{x}, {y}, {width}, {height}] does not fit the device's sensor of "
                f"{sensor_w}x{sensor_h} (OffsetX + Width <= {sensor_w}, "
                f"OffsetY + Height <= {sensor_h})"
            )
        for key, feature, value, step in (
            ("region x", "OffsetX", x, camera.get_x_offset_increment()),
            ("region y", "OffsetY", y, camera.get_y_offset_increment()),
            ("region width", "Width", width, camera.get_width_increment()),
            ("region height", "Height", height, camera.get_height_increment()),
        ):
            if step > 1 and value % step:
                raise DeviceError(f"{key} {value} is not a multiple of {feature}'s step {step}")
        self._apply("region", "OffsetX/OffsetY/Width/Height", lambda: camera.set_region(*region))
        got = tuple(int(v) for v in camera.get_region())
        if got != region:
            raise DeviceError(f"region: asked for {list(region)}, the device set {list(got)}")

    def _set_trigger(self, camera: Any) -> None:
        s = self.settings
        if s.trigger == "free_run":
            self._apply("trigger", "TriggerMode", camera.clear_triggers)
            return
        if not camera.is_software_trigger_supported() and s.trigger == "software":
            raise DeviceError("trigger: the device has no TriggerSoftware command")
        sources = [str(v) for v in camera.dup_available_trigger_sources() or []]
        source = "Software" if s.trigger == "software" else str(s.trigger_source)
        if source not in sources:
            key = "trigger" if s.trigger == "software" else "trigger_source"
            raise DeviceError(f"{key}: the device's TriggerSource offers {sources}, not {source!r}")
        self._apply(
            "trigger",
            "TriggerSelector/TriggerMode/TriggerSource",
            lambda: camera.set_trigger(source),
        )

    def _set_packet_size(self, camera: Any) -> None:
        s = self.settings
        if s.packet_size is None:
            self._apply("packet_size", "GevSCPSPacketSize", camera.gv_auto_packet_size)
            return
        device = camera.get_device()
        bounds = device.get_integer_feature_bounds("GevSCPSPacketSize")
        self._check_range("packet_size", "GevSCPSPacketSize", s.packet_size, bounds, " bytes")
        self._apply(
            "packet_size", "GevSCPSPacketSize", lambda: camera.gv_set_packet_size(s.packet_size)
        )

    # -- read ------------------------------------------------------------------------------

    def _read(self, timeout_s: float) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
        camera, stream, arv = self._camera, self._stream, self._arv
        assert camera is not None
        assert stream is not None
        trigger = self.settings.trigger
        deadline = self._clock.monotonic() + max(timeout_s, 0.0)
        if trigger != "hardware":
            self._drop_stale_buffers(stream)
        fire = trigger == "software"
        incomplete = 0
        while True:
            if fire:
                self._fire(camera)
                fire = False
            # A software trigger that got no frame is fired again after a while: a device
            # ignores TriggerSoftware while its acquisition is not yet running, and a frame
            # the second trigger makes too many is dropped as stale by the next grab.
            wait_until = deadline
            if trigger == "software":
                wait_until = min(deadline, self._clock.monotonic() + _REFIRE_AFTER_S)
            buffer = self._pop(stream, wait_until)
            if buffer is None and wait_until < deadline:
                fire = True
                continue
            if buffer is None:
                if self._control_lost.is_set():
                    raise DeviceError(f"{self._who()} stopped answering (heartbeat lost)")
                if not self._still_connected(camera):
                    raise DeviceError(f"{self._who()} stopped answering")
                cause = (
                    f"no trigger on {self.settings.trigger_source}"
                    if trigger == "hardware"
                    else "no complete frame"
                    if incomplete
                    else "no frame"
                )
                lost = f" ({incomplete} arrived incomplete)" if incomplete else ""
                raise FrameTimeout(f"{cause} from {self._who()} within {timeout_s:.3g} s{lost}")
            try:
                status = buffer.get_status()
                if status != arv.BufferStatus.SUCCESS:
                    incomplete += 1
                    if trigger == "hardware":
                        raise FrameTimeout(
                            f"frame {buffer.get_frame_id()} from {self._who()} arrived "
                            f"incomplete ({status.value_nick}): its trigger is lost"
                        )
                    fire = trigger == "software"
                    continue
                color = self._pixels(buffer)
                last = {
                    "frame_id": int(buffer.get_frame_id()),
                    "timestamp_ns": int(buffer.get_timestamp()),
                    "region": [
                        int(buffer.get_image_x()),
                        int(buffer.get_image_y()),
                        int(buffer.get_image_width()),
                        int(buffer.get_image_height()),
                    ],
                }
                with self._state_lock:
                    self._last_frame = last
            finally:
                stream.push_buffer(buffer)
            k = self.intrinsics
            if k is not None and (color.shape[1], color.shape[0]) != (k.width, k.height):
                raise DeviceError(
                    f"frames are {color.shape[1]}x{color.shape[0]} but the intrinsics are for "
                    f"{k.width}x{k.height}"
                )
            return color, None

    def _fire(self, camera: Any) -> None:
        if self._control_lost.is_set():
            raise DeviceError(f"{self._who()} stopped answering (heartbeat lost)")
        try:
            camera.software_trigger()
        except Exception as exc:  # noqa: BLE001 - GLib.GError: a GVCP write timed out
            # Aravis retries a GVCP write for seconds before it gives up: the device is gone.
            raise DeviceError(
                f"{self._who()} stopped answering (TriggerSoftware: {_error_text(exc)})"
            ) from exc

    def _pop(self, stream: Any, deadline: float) -> Any:
        """The next buffer before ``deadline`` (camera clock), or None."""
        while True:
            left_us = int((deadline - self._clock.monotonic()) * 1e6)
            if left_us <= 0 or self._control_lost.is_set():
                return None
            buffer = stream.timeout_pop_buffer(min(left_us, _POP_SLICE_US))
            if buffer is not None:
                return buffer

    def _pixels(self, buffer: Any) -> NDArray[np.uint8]:
        code = int(buffer.get_image_pixel_format())
        name = PIXEL_FORMAT_NAMES.get(code)
        if name is None:
            raise FrameTimeout(f"{self._who()} sent pixel format 0x{code:08x}, not supported")
        try:
            return convert_pixels(
                np.frombuffer(buffer.get_data(), dtype=np.uint8),
                pixel_format=name,
                width=int(buffer.get_image_width()),
                height=int(buffer.get_image_height()),
            )
        except ValueError as exc:
            raise FrameTimeout(f"{self._who()} gave an unusable frame: {exc}") from exc

    @staticmethod
    def _drop_stale_buffers(stream: Any) -> None:
        while True:
            stale = stream.try_pop_buffer()
            if stale is None:
                return
            stream.push_buffer(stale)

    @staticmethod
    def _still_connected(camera: Any) -> bool:
        """A register read answers (a GigE heartbeat in effect)."""
        try:
            camera.get_payload()
        except Exception:  # noqa: BLE001 - GLib.GError: timeout, transfer error
            return False
        return True

    # -- statistics and disconnect ---------------------------------------------------------

    def _stream_counts(self) -> dict[str, int]:
        """This stream's statistics (called under the state lock)."""
        stream = self._stream
        if stream is None:
            return dict.fromkeys(STREAM_COUNTERS, 0)
        counts = {}
        for key, info in STREAM_COUNTERS.items():
            try:
                counts[key] = int(stream.get_info_uint64_by_name(info))
            except Exception:  # noqa: BLE001 - a stream type without the counter
                counts[key] = 0
        return counts

    def status(self) -> dict[str, Any]:
        status = super().status()
        with self._state_lock:
            current = self._stream_counts()
            status["stream"] = {k: self._totals[k] + current[k] for k in STREAM_COUNTERS}
            status["last_frame"] = self._last_frame
        return status

    def _disconnect(self) -> None:
        camera, self._camera = self._camera, None
        with self._state_lock:
            for key, count in self._stream_counts().items():
                self._totals[key] += count
            stream, self._stream = self._stream, None
        # Each step runs even when the one before failed: the device may already be gone.
        if camera is not None:
            with contextlib.suppress(Exception):
                camera.stop_acquisition()
            # Control is given back now, not when the last reference to the device goes
            # (an error's traceback may hold one for a while): another server, or this
            # camera after a reload, may take the device at once.
            with contextlib.suppress(Exception):
                if camera.is_gv_device():
                    camera.get_device().leave_control()
        del stream
        # Dropping the last reference closes the device and gives up its control.
        del camera
