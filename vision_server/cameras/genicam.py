"""The ``genicam`` source: a GenICam camera (GigE Vision, USB3 Vision) through harvesters.

harvesters (and the genicam binding it depends on) is an optional extra (``pip install
'cellvision[genicam]'``), imported when the camera first connects. It loads the vendor's GenTL
producer (the ``cti`` file), opens the device with the configured serial, sets PixelFormat,
ExposureTime, Gain and the frame-start trigger (each checked against the device's own range or
entries first, so a refusal names the key and the range), and starts acquisition.

A grab, by ``trigger``:

- ``free_run``: drops the buffers the device filled before the grab, then takes the next one.
- ``software``: drops them, fires TriggerSoftware, takes the frame it triggered.
- ``hardware``: takes the next frame the line triggered, in trigger order (a frame triggered
  just before the grab is the one the PLC asked for, so it is not dropped).

A late frame raises ``CameraUnavailable`` and leaves the device connected; a device that no
longer answers a register read (a GigE camera unplugged or rebooted) is disconnected and
reconnected later (see :mod:`vision_server.cameras.device`). The device reports no
intrinsics: give them in the configuration for measuring inspections.

Not tried on a device: see README.md ("Real devices").
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .base import public_path
from .clock import Clock
from .device import DeviceCamera, DeviceError, FrameTimeout, import_sdk
from .pixels import convert_pixels
from .settings import GenICamCameraSettings

__all__ = ["GenICamCamera"]

_DRAIN_TIMEOUT_S = 0.001
"""How long a stale-buffer check waits: buffers already filled are there at once."""
_MAX_STALE_BUFFERS = 64


class GenICamCamera(DeviceCamera):
    """A GenICam camera through harvesters (see the module)."""

    source = "genicam"

    @property
    def triggered(self) -> bool:
        """A software or hardware trigger: the live view must not fire or take one."""
        return self.settings.trigger != "free_run"

    def __init__(
        self,
        name: str,
        settings: GenICamCameraSettings,
        *,
        base_dir: Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(
            name,
            intrinsics=settings.intrinsics,
            has_depth=False,
            reconnect_interval_s=settings.reconnect_interval_s,
            clock=clock,
        )
        self.settings = settings
        cti = settings.cti.expanduser()
        if not cti.is_absolute() and base_dir is not None:
            cti = base_dir / cti
        self.cti_path = cti
        self.hide_path(cti, public_path(settings.cti))
        self._harvester: Any = None
        self._acquirer: Any = None
        self._gentl: ModuleType | None = None

    # -- connect ---------------------------------------------------------------------------

    def _connect(self) -> None:
        core = import_sdk("harvesters.core", extra="genicam")
        self._gentl = import_sdk("genicam.gentl", extra="genicam")
        if not self.cti_path.is_file():
            raise DeviceError(f"the GenTL producer {self.cti_path} does not exist")
        try:
            harvester = self._harvester = core.Harvester()
            harvester.add_file(str(self.cti_path))
            harvester.update()
            infos = list(harvester.device_info_list)
        except Exception as exc:  # noqa: BLE001 - the producer's errors have no common base
            raise DeviceError(f"loading the GenTL producer {self.cti_path} failed: {exc}") from exc
        serial, model = self._pick_device(infos)
        try:
            self._acquirer = harvester.create({"serial_number": serial})
        except Exception as exc:  # noqa: BLE001 - e.g. the device is open in another process
            raise DeviceError(f"opening GenICam device {serial} failed: {exc}") from exc
        self._device_info = {"serial": serial, "model": model}
        self._configure()
        try:
            self._acquirer.start()
        except Exception as exc:  # noqa: BLE001
            raise DeviceError(f"starting acquisition on {serial} failed: {exc}") from exc

    def _pick_device(self, infos: list[Any]) -> tuple[str, str]:
        found = {str(info.serial_number): str(info.model) for info in infos}
        listed = ", ".join(sorted(found)) or "none"
        wanted = self.settings.serial
        # A producer that fails to load lists no device (harvesters only logs it): name it.
        through = f"through {self.cti_path}"
        if wanted is None:
            if len(found) != 1:
                what = "no GenICam device is visible" if not found else "several are visible"
                raise DeviceError(f"{what} {through} (serials: {listed}); set serial to choose one")
            return next(iter(found.items()))
        if wanted not in found:
            raise DeviceError(
                f"no GenICam device with serial {wanted} {through} (visible: {listed})"
            )
        return wanted, found[wanted]

    def _node(self, feature: str) -> Any:
        """The node of ``feature`` in the device's node map, or None if it has none."""
        try:
            return getattr(self._acquirer.remote_device.node_map, feature)
        except Exception:  # noqa: BLE001 - a missing feature raises the binding's own error
            return None

    def _set(self, key: str, feature: str, value: Any) -> None:
        """Set ``feature`` to ``value``; ``key`` is the configuration's name for it."""
        node = self._node(feature)
        if node is None:
            raise DeviceError(f"{key}: the device has no {feature} feature")
        if isinstance(value, str):
            entries = [str(entry) for entry in getattr(node, "symbolics", ())]
            if entries and value not in entries:
                raise DeviceError(f"{key}: the device's {feature} offers {entries}, not {value!r}")
        else:
            low, high = float(node.min), float(node.max)
            if not low <= value <= high:
                raise DeviceError(
                    f"{key} {value:g} is outside the device's {feature} range [{low:g}, {high:g}]"
                )
        try:
            node.value = value
        except Exception as exc:  # noqa: BLE001 - genapi's OutOfRange/Access exceptions
            raise DeviceError(f"{key}: the device refused {feature} = {value!r}: {exc}") from exc

    def _configure(self) -> None:
        s = self.settings
        self._set("pixel_format", "PixelFormat", s.pixel_format)
        if s.exposure_us is not None:
            if self._node("ExposureAuto") is not None:
                self._set("exposure_us", "ExposureAuto", "Off")
            self._set("exposure_us", "ExposureTime", s.exposure_us)
        if s.gain_db is not None:
            if self._node("GainAuto") is not None:
                self._set("gain_db", "GainAuto", "Off")
            self._set("gain_db", "Gain", s.gain_db)
        if self._node("TriggerSelector") is not None:
            self._set("trigger", "TriggerSelector", "FrameStart")
        if s.trigger == "free_run":
            self._set("trigger", "TriggerMode", "Off")
            return
        self._set("trigger", "TriggerMode", "On")
        if s.trigger == "software":
            self._set("trigger", "TriggerSource", "Software")
            if self._node("TriggerSoftware") is None:
                raise DeviceError("trigger: the device has no TriggerSoftware command")
        else:
            assert s.trigger_source is not None
            self._set("trigger_source", "TriggerSource", s.trigger_source)

    # -- read ------------------------------------------------------------------------------

    def _read(self, timeout_s: float) -> tuple[NDArray[np.uint8], NDArray[np.uint16] | None]:
        gentl = self._gentl
        assert gentl is not None
        acquirer = self._acquirer
        trigger = self.settings.trigger
        try:
            if trigger != "hardware":
                self._drop_stale_buffers()
            if trigger == "software":
                self._node("TriggerSoftware").execute()
            buffer = acquirer.fetch(timeout=max(timeout_s, _DRAIN_TIMEOUT_S))
        except gentl.TimeoutException as exc:
            if not self._still_connected():
                raise DeviceError(f"GenICam device {self._serial()} stopped answering") from exc
            what = "no trigger on " + str(self.settings.trigger_source)
            cause = what if trigger == "hardware" else "no frame"
            raise FrameTimeout(f"{cause} from {self._serial()} within {timeout_s:.3g} s") from exc
        except Exception as exc:  # noqa: BLE001 - any other transport error: the device is lost
            raise DeviceError(f"GenICam device {self._serial()} failed: {exc}") from exc
        try:
            component = buffer.payload.components[0]
            fmt = str(getattr(component, "data_format", self.settings.pixel_format))
            color = convert_pixels(
                component.data,
                pixel_format=fmt,
                width=int(component.width),
                height=int(component.height),
            )
        except (ValueError, IndexError, AttributeError) as exc:
            raise FrameTimeout(f"{self._serial()} gave an unusable buffer: {exc}") from exc
        finally:
            buffer.queue()  # hand the buffer back to the producer's pool
        k = self.intrinsics
        if k is not None and (color.shape[1], color.shape[0]) != (k.width, k.height):
            raise DeviceError(
                f"frames are {color.shape[1]}x{color.shape[0]} but the intrinsics are for "
                f"{k.width}x{k.height}"
            )
        return color, None

    def _drop_stale_buffers(self) -> None:
        for _ in range(_MAX_STALE_BUFFERS):
            stale = self._acquirer.try_fetch(timeout=_DRAIN_TIMEOUT_S)
            if stale is None:
                return
            stale.queue()

    def _still_connected(self) -> bool:
        """A register read answers (a GigE heartbeat in effect)."""
        try:
            _ = self._acquirer.remote_device.node_map.PixelFormat.value
        except Exception:  # noqa: BLE001 - IoException, TimeoutException, AccessException ...
            return False
        return True

    def _serial(self) -> str:
        return str(self._device_info.get("serial", "?"))

    def _disconnect(self) -> None:
        acquirer, self._acquirer = self._acquirer, None
        harvester, self._harvester = self._harvester, None
        # Each step runs even when the one before failed: the device may already be gone.
        if acquirer is not None:
            for step in (acquirer.stop, acquirer.destroy):
                with contextlib.suppress(Exception):
                    step()
        if harvester is not None:
            with contextlib.suppress(Exception):
                harvester.reset()
