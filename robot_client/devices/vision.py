"""The vision client as a device: :class:`LazyVision` (connects on first use, so skills that
never look need no server) and :class:`ServerCamera` (a server camera read with CAPTURE, placed
on the robot's tool or fixed in the cell)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import CameraIntrinsics
from protocol import Frames, ImageRole, UnexpectedMessage, array_from_payload

from ..client import SyncVisionClient
from . import Capture, DeviceError, Robot, Vision

__all__ = ["LazyVision", "ServerCamera", "intrinsics_from_dict"]

FloatArray = NDArray[np.float64]


class LazyVision:
    """A :class:`~robot_client.devices.Vision` that opens a :class:`SyncVisionClient` on its
    first request (``factory`` builds it; keyword arguments go to SyncVisionClient)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 7878,
        *,
        factory: Callable[[], Vision] | None = None,
        **kwargs: Any,
    ) -> None:
        self.host, self.port = host, port
        self._factory: Callable[[], Vision] = factory or (
            lambda: SyncVisionClient(host, port, **kwargs)
        )
        self._client: Vision | None = None

    @property
    def client(self) -> Vision:
        if self._client is None:
            self._client = self._factory()
        return self._client

    @property
    def connected(self) -> bool:
        return self._client is not None

    def ping(self, data: str = "") -> float:
        return self.client.ping(data)

    def list_inspections(self) -> tuple[dict[str, Any], ...]:
        return self.client.list_inspections()

    def inspect(self, inspection: str, image: Any = None, **kwargs: Any) -> Any:
        return self.client.inspect(inspection, image, **kwargs)

    def capture(self, camera: str, **kwargs: Any) -> Any:
        return self.client.capture(camera, **kwargs)

    def operator_call(self, message: str, **kwargs: Any) -> Any:
        """Ask the person at the server's console (see SyncVisionClient.operator_call)."""
        call = getattr(self.client, "operator_call", None)
        if call is None:
            raise UnexpectedMessage("this vision client cannot post operator calls")
        return call(message, **kwargs)

    def close(self) -> None:
        closer = getattr(self._client, "close", None)
        if callable(closer):
            closer()
        self._client = None


def intrinsics_from_dict(data: dict[str, Any]) -> CameraIntrinsics:
    """The ``intrinsics`` object of a FRAMES message (SPEC §6.4) as :class:`CameraIntrinsics`.

    ``dist`` is OpenCV's coefficient vector (5 to 14 numbers, k1, k2, p1, p2, k3 first; absent
    = none).
    The client's camera model has five (k1, k2, p1, p2, k3): coefficients beyond them must be 0,
    or the camera cannot be modelled here and DeviceError says so (never silently dropped).
    """
    try:
        coefficients = [float(d) for d in data.get("dist", ())]
        if coefficients and not 4 <= len(coefficients) <= 14:
            raise ValueError(
                f"dist has {len(coefficients)} coefficients; OpenCV's model has 4 to 14"
            )
        extra = coefficients[5:]
        if any(extra):
            raise ValueError(
                "the camera's distortion has rational/thin-prism/tilt terms (k4 and on), which "
                "this client's five-coefficient model cannot apply"
            )
        dist = (coefficients + [0.0] * 5)[:5]
        return CameraIntrinsics(
            width=int(data["width"]),
            height=int(data["height"]),
            fx=float(data["fx"]),
            fy=float(data["fy"]),
            cx=float(data["cx"]),
            cy=float(data["cy"]),
            dist=(dist[0], dist[1], dist[2], dist[3], dist[4]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DeviceError(f"bad camera intrinsics from the server: {exc}") from exc


class ServerCamera:
    """A camera attached to the vision server, read with CAPTURE.

    Give ``tool_from_camera`` for a camera on the tool (its pose follows the robot) or
    ``base_from_camera`` (mount base frame) for a fixed one.
    """

    def __init__(
        self,
        vision: Vision,
        name: str,
        robot: Robot,
        *,
        tool_from_camera: ArrayLike | None = None,
        base_from_camera: ArrayLike | None = None,
        intrinsics: CameraIntrinsics | None = None,
    ) -> None:
        if (tool_from_camera is None) == (base_from_camera is None):
            raise ValueError("give exactly one of tool_from_camera and base_from_camera")
        self.vision, self.name, self.robot = vision, name, robot
        self._tool_from_camera = (
            None if tool_from_camera is None else np.asarray(tool_from_camera, np.float64)
        )
        self._base_from_camera = (
            None if base_from_camera is None else np.asarray(base_from_camera, np.float64)
        )
        self._intrinsics = intrinsics

    @property
    def tool_from_camera(self) -> FloatArray | None:
        return None if self._tool_from_camera is None else self._tool_from_camera.copy()

    @property
    def intrinsics(self) -> CameraIntrinsics:
        if self._intrinsics is None:
            self.capture()
        assert self._intrinsics is not None
        return self._intrinsics

    def capture(self, *, depth_frames: int = 0) -> Capture:
        if depth_frames < 0:
            raise ValueError(f"depth_frames must be >= 0, got {depth_frames}")
        base_from_user = self.robot.base_frame()
        if self._tool_from_camera is not None:
            base_from_camera = base_from_user @ self.robot.base_from_tool() @ self._tool_from_camera
        else:
            assert self._base_from_camera is not None
            base_from_camera = self._base_from_camera.copy()
        frames: Frames = self.vision.capture(
            self.name, count=max(1, depth_frames), depth=depth_frames > 0
        )
        colors = [p for p in frames.images if p.role is ImageRole.COLOR]
        depths = [p for p in frames.images if p.role is ImageRole.DEPTH]
        if not colors:
            raise DeviceError(f"server camera {self.name!r} sent no colour image")
        if len(depths) < depth_frames:
            raise DeviceError(
                f"server camera {self.name!r} sent {len(depths)} depth frames, {depth_frames} asked"
            )
        if frames.intrinsics is not None:
            self._intrinsics = intrinsics_from_dict(frames.intrinsics)
        if self._intrinsics is None:
            raise DeviceError(f"server camera {self.name!r} does not report its intrinsics")
        return Capture(
            color=array_from_payload(colors[0]),
            depth=tuple(array_from_payload(d) for d in depths[:depth_frames]),
            intrinsics=self._intrinsics,
            base_from_camera=base_from_camera,
            base_from_user=base_from_user,
            camera=self.name,
        )
