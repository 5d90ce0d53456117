"""The robot-driven sensor check: the RGB-D camera on the tool looks at the QR board from a few
directions, and the server's ``qr_pose`` inspection says at each how far the depth puts the
code from where its printed side does; one fit over the views gives the depth camera's scale
error and its depth-to-colour shift (the model and fit of ``vision-server sensor-check``,
:mod:`geometry.depth_registration`).

The shift shows only through the board's tilt, so the views turn the camera about the code's
centre by ``tilt_deg`` towards directions spread all round (the distance kept). The
``qr_pose`` inspection must apply no depth correction of its own (no ``depth_scale`` /
``depth_shift_px``): the check measures the raw sensor.

Frames: the robot's base frame for tool poses, the QR frame of docs/conventions.md (origin
at the code's centre, z into the print); metres, radians, pixels.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry.depth_registration import (
    DepthRegistration,
    fit_depth_registration,
    registration_advice,
)

from ..devices import Devices
from .collect import move_to_view
from .hand_eye import plan_views

__all__ = ["SensorCheck", "SensorView", "check_sensor"]

FloatArray = NDArray[np.float64]
ProgressFn = Callable[[str, float], None]
# The code's centre frame with z out of the print, towards the camera (the QR frame's z points
# into the print): the frame plan_views aims at.
_QR_FROM_CENTRE = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class SensorView:
    """One view's share of the fit: ``depth_vs_side`` (relative), its gain per pixel of
    shift ``shift_sensitivity`` (u, v), the code's side in the image ``side_px`` and
    ``depth_vs_grid``, the disagreement from the code's module grid (NaN: not reported; the
    fit prefers it, :func:`geometry.depth_registration.fit_depth_registration`)."""

    label: str
    depth_vs_side: float
    shift_sensitivity: tuple[float, float]
    side_px: float
    depth_vs_grid: float = math.nan


@dataclass
class SensorCheck:
    """The views used, those skipped (label, why), the fit and the advice (``ok``: within
    the limits of :mod:`geometry.depth_registration`)."""

    views: list[SensorView] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    registration: DepthRegistration | None = None
    ok: bool = False
    advice: str = ""


def _number(value: Any) -> float:
    return float(value) if isinstance(value, int | float) else math.nan


def _sensor_view(data: Mapping[str, Any], label: str) -> tuple[SensorView | None, str]:
    """The view from a ``qr_pose`` RESULT's data, or (None, why it cannot be used)."""
    if not data.get("found"):
        return None, str(data.get("reason") or "no QR code")
    quality = data.get("quality") or {}
    ratio = _number(quality.get("depth_vs_side"))
    gains = quality.get("shift_sensitivity") or []
    side_px = _number(quality.get("side_px"))
    if not math.isfinite(ratio) or len(gains) != 2 or not math.isfinite(side_px):
        return None, "no depth_vs_side in the quality report: give the qr_pose inspection side_m"
    grid = _number(quality.get("depth_vs_grid"))
    return SensorView(label, ratio, (_number(gains[0]), _number(gains[1])), side_px, grid), ""


def _camera_from_qr(data: Mapping[str, Any]) -> FloatArray:
    pose = np.asarray(data.get("camera_from_qr"), dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError("the qr_pose inspection returned no camera_from_qr")
    return pose


def check_sensor(
    devices: Devices,
    *,
    camera: str,
    inspection: str,
    views: int = 12,
    tilt_deg: float = 22.0,
    depth_frames: int = 5,
    corner_bias_px: float = 0.0,
    progress: ProgressFn | None = None,
) -> SensorCheck:
    """Move the RGB-D ``camera`` (on the tool) through ``views`` views of the QR board tilted
    by up to ``tilt_deg`` about the code's centre, capture colour and ``depth_frames`` depth
    frames at each, run ``inspection`` (a ``qr_pose`` with ``side_m``, no depth correction)
    and fit the depth scale and shift; ``corner_bias_px`` as that inspection's. The robot
    must start where the camera sees the code; it returns there at the end. Raises
    ``ValueError`` for a camera that is not on the tool or has no depth, or when the code is
    not in view at the start; the fit's ``ValueError`` (fewer than 2 usable views) too."""
    device = devices.camera(camera)
    tool_from_camera = device.tool_from_camera
    if tool_from_camera is None:
        raise ValueError(f"camera {camera!r} is not on the tool: the robot cannot turn it")
    # Not in the Camera protocol: devices that say so are refused here; for the others the
    # first capture raises ValueError (depth frames from a camera without depth).
    if not getattr(device, "has_depth", True):
        raise ValueError(f"camera {camera!r} has no depth sensor to check")
    if devices.vision is None:
        raise ValueError(f"no vision server to run the qr_pose inspection {inspection!r} on")
    vision = devices.vision
    start_pose = devices.robot.base_from_tool()
    first = device.capture(depth_frames=depth_frames)
    data = vision.inspect(inspection, first.color, depth=list(first.depth)).data
    if not data.get("found"):
        raise ValueError(
            f"the QR code is not in view of camera {camera!r} at the start "
            f"({data.get('reason') or 'not found'}): move the robot so that the camera sees it"
        )
    camera_from_qr = _camera_from_qr(data)
    base_from_centre = first.base_from_camera @ camera_from_qr @ _QR_FROM_CENTRE
    poses = plan_views(
        base_from_centre,
        tool_from_camera,
        count=views,
        distance_m=float(np.linalg.norm(camera_from_qr[:3, 3])),
        tilt_rad=math.radians(tilt_deg),
        roll_rad=0.0,
        depth_spread=0.0,
    )
    check = SensorCheck()
    try:
        for i, pose in enumerate(poses):
            label = f"view {i + 1}"
            if progress is not None:
                progress(f"{label} of {len(poses)}", i / len(poses))
            refused = move_to_view(devices, pose)
            if refused is not None:
                check.skipped.append((label, refused))
                continue
            cap = device.capture(depth_frames=depth_frames)
            found, why = _sensor_view(
                vision.inspect(inspection, cap.color, depth=list(cap.depth)).data, label
            )
            if found is None:
                check.skipped.append((label, why))
                continue
            check.views.append(found)
    finally:
        devices.robot.move_linear(start_pose)
    check.registration = fit_depth_registration(
        [v.depth_vs_side for v in check.views],
        [v.shift_sensitivity for v in check.views],
        [v.side_px for v in check.views],
        corner_bias_px=corner_bias_px,
        depth_vs_grid=[v.depth_vs_grid for v in check.views],
    )
    check.ok, check.advice = registration_advice(check.registration)
    if progress is not None:
        progress(f"{len(check.views)} views", 1.0)
    return check
