"""Calibrated camera mounts in the teach store: where a hand-eye calibration is kept and how
skills see it.

``robot-client calibrate-hand-eye`` stores one record per camera (skill ``hand_eye``, name =
the camera's name) with the camera's pose (``tool_from_camera`` for a camera on the tool,
``base_from_camera`` in the robot's mount base frame for a fixed one), the intrinsics the
calibration was made with (the pose is only right with them), its date, verdict and residuals::

    - skill: hand_eye
      name: tool_camera
      taught_at: "2026-11-24T16:30:00Z"
      notes: "good: reprojection RMS 0.18 px over 15 views"
      params:
        setup: eye_in_hand
        tool_from_camera: {xyz: [0.07, 0.0, -0.1], rpy: [0.0, 0.0, 0.0]}
        intrinsics: {width: 1024, height: 768, fx: ..., distortion: [...]}
        verdict: good
        rms_px: 0.18
        ...

:meth:`SkillContext.camera <robot_client.skills.base.SkillContext.camera>` wraps a camera
that has such a record in :class:`CalibratedCamera`, so vision pick, QR calibration and quality
control use the calibrated pose and intrinsics instead of the device's nominal ones.
Metres, radians, pixels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, invert_transform

from ..devices import Camera, Capture
from .record import ParamError, TaughtRecord, pose_from_yaml, pose_to_yaml, utc_now_iso

__all__ = [
    "HAND_EYE_SKILL",
    "CalibratedCamera",
    "StoredHandEye",
    "hand_eye_record",
    "stored_hand_eye",
]

FloatArray = NDArray[np.float64]
HandEyeSetup = Literal["eye_in_hand", "eye_to_hand"]
HAND_EYE_SKILL = "hand_eye"
_POSE_KEY: dict[str, str] = {"eye_in_hand": "tool_from_camera", "eye_to_hand": "base_from_camera"}


@dataclass(frozen=True)
class StoredHandEye:
    """A camera's calibrated mount: ``pose`` is ``tool_from_camera`` (eye-in-hand) or
    ``base_from_camera`` (eye-to-hand, the robot's mount base frame); ``intrinsics`` those
    the calibration used (None: the device's own)."""

    camera: str
    setup: HandEyeSetup
    pose: FloatArray
    intrinsics: CameraIntrinsics | None
    verdict: str
    taught_at: str


def _intrinsics_to_yaml(k: CameraIntrinsics) -> dict[str, Any]:
    return {
        "width": k.width,
        "height": k.height,
        "fx": float(k.fx),
        "fy": float(k.fy),
        "cx": float(k.cx),
        "cy": float(k.cy),
        "distortion": [float(d) for d in k.dist],
    }


def _intrinsics_from_yaml(value: Any) -> CameraIntrinsics:
    if not isinstance(value, Mapping):
        raise ValueError(f"intrinsics: expected a mapping, got {value!r}")
    try:
        k1, k2, p1, p2, k3 = (float(d) for d in value.get("distortion", [0.0] * 5))
        return CameraIntrinsics(
            int(value["width"]),
            int(value["height"]),
            float(value["fx"]),
            float(value["fy"]),
            float(value["cx"]),
            float(value["cy"]),
            (k1, k2, p1, p2, k3),
        )
    except KeyError as exc:
        raise ValueError(f"intrinsics: missing {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f"intrinsics: {exc}") from None


def hand_eye_record(
    camera: str,
    setup: HandEyeSetup,
    pose: FloatArray,
    *,
    intrinsics: CameraIntrinsics,
    verdict: str,
    reasons: Sequence[str],
    figures: Mapping[str, Any],
) -> TaughtRecord:
    """The teach-store record of a hand-eye calibration of ``camera`` made now: ``pose`` as
    in :class:`StoredHandEye`; ``figures`` the residuals to keep with it (plain values)."""
    params: dict[str, Any] = {
        "setup": setup,
        _POSE_KEY[setup]: pose_to_yaml(pose),
        "intrinsics": _intrinsics_to_yaml(intrinsics),
        "verdict": verdict,
        **figures,
    }
    note = f"{verdict}: " + "; ".join(reasons)
    return TaughtRecord(HAND_EYE_SKILL, camera, params, taught_at=utc_now_iso(), notes=note)


def stored_hand_eye(records: Sequence[TaughtRecord], camera: str) -> StoredHandEye | None:
    """The calibrated mount of ``camera`` among ``records`` (None: not calibrated); raises
    ``ValueError`` naming the record and the key when the record is malformed."""
    for record in records:
        if record.skill == HAND_EYE_SKILL and record.name == camera:
            break
    else:
        return None
    where = f"record {record.key}"
    setup = record.params.get("setup")
    if setup not in _POSE_KEY:
        raise ValueError(f"{where}: setup must be eye_in_hand or eye_to_hand, got {setup!r}")
    key = _POSE_KEY[setup]
    try:
        pose = pose_from_yaml(record.params.get(key), f"{where}: {key}")
        intrinsics = (
            None
            if record.params.get("intrinsics") is None
            else _intrinsics_from_yaml(record.params["intrinsics"])
        )
    except ParamError as exc:
        raise ValueError(str(exc)) from None
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    return StoredHandEye(
        camera,
        setup,
        pose,
        intrinsics,
        str(record.params.get("verdict", "")),
        record.taught_at,
    )


class CalibratedCamera:
    """``camera`` with its mount (and intrinsics) from a hand-eye calibration: captures carry
    the calibrated ``base_from_camera``; everything else is the camera's own."""

    def __init__(self, camera: Camera, stored: StoredHandEye) -> None:
        nominal = camera.tool_from_camera
        if stored.setup == "eye_in_hand" and nominal is None:
            raise ValueError(
                f"record {HAND_EYE_SKILL}/{stored.camera}: calibrated on the tool, but the "
                "camera is a fixed one"
            )
        if stored.setup == "eye_to_hand" and nominal is not None:
            raise ValueError(
                f"record {HAND_EYE_SKILL}/{stored.camera}: calibrated as a fixed camera, but "
                "the camera is on the tool"
            )
        self.camera = camera
        self.stored = stored
        # The device's captures say where it thinks the camera is: undo its nominal mount to
        # get the tool pose the robot reported, then apply the calibrated one.
        self._tool_from_nominal = nominal

    def __getattr__(self, name: str) -> Any:
        return getattr(self.camera, name)  # has_depth, name, ... of the device

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self.stored.intrinsics or self.camera.intrinsics

    @property
    def tool_from_camera(self) -> FloatArray | None:
        return self.stored.pose.copy() if self.stored.setup == "eye_in_hand" else None

    def capture(self, *, depth_frames: int = 0) -> Capture:
        cap = self.camera.capture(depth_frames=depth_frames)
        if self._tool_from_nominal is not None:
            base_from_tool = cap.base_from_camera @ invert_transform(self._tool_from_nominal)
            base_from_camera = base_from_tool @ self.stored.pose
        else:
            base_from_camera = self.stored.pose.copy()
        return replace(cap, base_from_camera=base_from_camera, intrinsics=self.intrinsics)
