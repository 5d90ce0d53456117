"""``qr_pose``: the pose of a QR code, camera_from_qr, from one colour frame and N depth frames
(the paper's fast calibration, Table 3 and equations 1-4), with a quality report."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from protocol import BadImage
from yamlfile import Node, fraction, non_negative, numbers, one_of, positive
from yamlfile import number as to_number

from ..analysis import (
    UNCHECKED_SCALE_STD,
    UNCHECKED_SHIFT_STD_PX,
    AnalysisError,
    DepthError,
    NotFoundError,
    QRPoseQuality,
    qr_pose,
)
from ..cameras import CameraSettings
from .base import Common, Configured, analysis_failed, draw_verdict, overlay_base, parse_common
from .contract import InspectionInput, InspectionOutcome
from .kinds import Data, ResultKind, points
from .qr import parse_expect

MAX_CORNER_BIAS_PX = 1.0
"""A detector off by more than this is broken, not biased."""

MAX_UNCHECKED_SCALE_STD = 0.2
MAX_UNCHECKED_SHIFT_STD_PX = 50.0
"""Beyond these the depth is not a depth sensor's: a typo (1 for 1 %), not a sensor."""

RED = (0, 0, 255)
AXIS_COLOURS = ((0, 0, 255), (0, 200, 0), (255, 0, 0))  # x red, y green, z blue (BGR)


@dataclass(frozen=True)
class QRPoseInspection(Configured):
    common: Common
    method: str
    expect: Any
    side_m: float | None
    max_plane_rms_m: float | None
    min_valid_fraction: float | None
    depth_scale: float = 1.0
    depth_shift_px: tuple[float, float] = (0.0, 0.0)
    max_depth_vs_side: float = 0.003
    depth_scale_std: float | None = None
    depth_shift_std_px: tuple[float, float] = (0.0, 0.0)
    corner_bias_px: float | None = None
    unchecked_scale_std: float = UNCHECKED_SCALE_STD
    unchecked_shift_std_px: float = UNCHECKED_SHIFT_STD_PX

    type = "qr_pose"
    uses_depth = True

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        name = self.common.name
        if image.intrinsics is None:
            raise BadImage(
                f"inspection {name!r}: camera {self.common.camera!r} has no intrinsics; "
                "configure them (fx, fy, cx, cy, distortion)"
            )
        if not image.depth:
            raise BadImage(f"inspection {name!r} needs at least one depth frame")
        try:
            pose = qr_pose(
                image.color,
                list(image.depth),
                image.intrinsics.to_geometry(),
                method="corners" if self.method == "corners" else "plane",
                roi=self.common.roi,
                expect=self.expect,
                side_m=self.side_m,
                depth_scale=self.depth_scale,
                depth_shift_px=self.depth_shift_px,
                depth_scale_std=self.depth_scale_std,
                depth_shift_std_px=self.depth_shift_std_px,
                corner_bias_px=self.corner_bias_px,
                unchecked_scale_std=self.unchecked_scale_std,
                unchecked_shift_std_px=self.unchecked_shift_std_px,
            )
        except (NotFoundError, DepthError) as exc:
            picture = None
            if overlay:
                picture = draw_verdict(overlay_base(image.color, self.common.roi), False, str(exc))
            return InspectionOutcome(False, {"found": False, "reason": str(exc)}, picture)
        except AnalysisError as exc:
            raise analysis_failed(name, exc) from None
        quality = _quality(pose.quality)
        reasons = []
        rms = quality.get("plane_rms_m")
        if self.max_plane_rms_m is not None and rms is not None and rms > self.max_plane_rms_m:
            reasons.append(f"plane RMS {rms * 1000:.2f} mm above {self.max_plane_rms_m * 1000} mm")
        valid = quality.get("valid_depth_fraction")
        if (
            self.min_valid_fraction is not None
            and valid is not None
            and valid < self.min_valid_fraction
        ):
            reasons.append(f"valid depth fraction {valid:.2f} below {self.min_valid_fraction}")
        passed = not reasons
        quality["warnings"] = _warnings(quality, self.max_depth_vs_side)
        data: dict[str, Any] = {
            "found": True,
            "text": pose.text,
            "method": pose.method,
            "camera_from_qr": [[float(x) for x in row] for row in pose.camera_from_qr],
            "corners": [[float(u), float(v)] for u, v in pose.corners_uv],
            "corners_camera": [[float(c) for c in p] for p in pose.corners_camera],
            "quality": quality,
        }
        if reasons:
            data["reason"] = "; ".join(reasons)
        picture = None
        if overlay:
            picture = overlay_base(image.color, self.common.roi)
            pts = np.round(np.asarray(pose.corners_uv)).astype(np.int32)
            cv2.polylines(picture, [pts], True, RED, 2)
            self._draw_axes(picture, pose.camera_from_qr, image)
            t = pose.camera_from_qr[:3, 3]
            draw_verdict(picture, passed, f"{pose.text}  z = {t[2]:.3f} m")
        return InspectionOutcome(passed, data, picture)

    def _draw_axes(self, picture: Any, camera_from_qr: Any, image: InspectionInput) -> None:
        assert image.intrinsics is not None
        camera = image.intrinsics.to_geometry()
        length = self.side_m or 0.05
        origin = camera_from_qr[:3, 3]
        points = np.array([origin] + [origin + camera_from_qr[:3, i] * length for i in range(3)])
        uv = np.round(camera.project(points)).astype(int)
        for i in range(3):
            cv2.arrowedLine(picture, tuple(uv[0]), tuple(uv[i + 1]), AXIS_COLOURS[i], 2)


def _warnings(quality: dict[str, Any], limit: float) -> list[str]:
    """Warnings that do not fail the inspection: the depth disagrees with the printed side
    (a depth scale error or misregistration the camera's correction does not remove)."""
    mismatch = quality.get("depth_vs_side")
    if mismatch is None or abs(mismatch) <= limit:
        return []
    return [
        f"depth puts the code {mismatch * 100:+.2f} % from where its printed side does "
        f"(limit {limit * 100:.2f} %): the depth sensor is misregistered or its scale is off; "
        "run `vision-server sensor-check` and set depth_scale / depth_shift_px"
    ]


def _quality(quality: QRPoseQuality) -> dict[str, Any]:
    """The quality report as JSON (metres, radians)."""
    out: dict[str, Any] = {}
    for name in (
        "valid_depth_fraction",
        "plane_rms_m",
        "inlier_fraction",
        "orthogonality_rad",
        "side_m",
        "scale",
        "frames",
        "depth_vs_side",
        "depth_vs_grid",
        "side_px",
    ):
        value = getattr(quality, name, None)
        if value is None or isinstance(value, str):
            out[name] = value
        elif isinstance(value, int | np.integer) and not isinstance(value, bool):
            out[name] = int(value)
        else:
            number = float(value)
            out[name] = number if math.isfinite(number) else None  # NaN: not measured
    for name in ("corner_depth_std_m", "side_lengths_m", "shift_sensitivity"):
        values = np.asarray(getattr(quality, name), dtype=float)
        out[name] = [float(x) if math.isfinite(x) else None for x in values]
    return out


def parse_qr_pose(
    node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> QRPoseInspection:
    common = parse_common(node, "qr_pose", cameras, default_frames=5)
    settings = cameras[common.camera]
    if type(settings).__name__ == "RequestCameraSettings" and not getattr(settings, "depth", False):
        raise node.error(
            f"camera {common.camera!r} gets no depth (set depth: true on a request camera, or "
            "use an RGB-D camera)",
            "camera",
        )
    if type(settings).__name__ in ("FolderCameraSettings", "OpenCVCameraSettings") and not (
        getattr(settings, "depth_glob", None)
    ):
        raise node.error(f"camera {common.camera!r} delivers no depth frames", "camera")
    return QRPoseInspection(
        common,
        node.take("method", one_of("plane", "corners"), "plane"),
        parse_expect(node),
        node.take("side_m", positive, None),
        node.take("max_plane_rms_m", positive, None),
        node.take("min_valid_fraction", fraction, None),
        node.take("depth_scale", positive, 1.0),
        _pair(node.take("depth_shift_px", numbers(2), (0.0, 0.0))),
        node.take("max_depth_vs_side", positive, 0.003),
        node.take("depth_scale_std", non_negative, None),
        _pair(node.take("depth_shift_std_px", numbers(2, each=non_negative), (0.0, 0.0))),
        node.take("corner_bias_px", _corner_bias, None),
        node.take("unchecked_scale_std", _unchecked_scale_std, UNCHECKED_SCALE_STD),
        node.take("unchecked_shift_std_px", _unchecked_shift_std, UNCHECKED_SHIFT_STD_PX),
    )


def _corner_bias(value: Any) -> float:
    """The corner detector's bias on the code's image side, pixels (a small number)."""
    bias = to_number(value)
    if not math.isfinite(bias) or abs(bias) > MAX_CORNER_BIAS_PX:
        raise ValueError(f"expected a bias within +/-{MAX_CORNER_BIAS_PX:g} px, got {value!r}")
    return bias


def _unchecked_scale_std(value: Any) -> float:
    """The relative depth scale std assumed of an unchecked sensor (0.01 = 1 %)."""
    std = non_negative(value)
    if not math.isfinite(std) or std > MAX_UNCHECKED_SCALE_STD:
        raise ValueError(
            f"expected a relative std from 0 to {MAX_UNCHECKED_SCALE_STD:g} (0.01 = 1 %), "
            f"got {value!r}"
        )
    return float(std)


def _unchecked_shift_std(value: Any) -> float:
    """The depth-to-colour registration std assumed of an unchecked sensor, pixels."""
    std = non_negative(value)
    if not math.isfinite(std) or std > MAX_UNCHECKED_SHIFT_STD_PX:
        raise ValueError(
            f"expected a std from 0 to {MAX_UNCHECKED_SHIFT_STD_PX:g} px, got {value!r}"
        )
    return float(std)


def _pair(values: tuple[float, ...]) -> tuple[float, float]:
    return (float(values[0]), float(values[1]))


def _qr_pose_expected(data: Data) -> dict[str, Any]:
    if not data.get("found"):
        return {}
    return {
        "text": data["text"],
        "corners": points(data["corners"]),
        "camera_from_qr": [[round(x, 6) for x in row] for row in data["camera_from_qr"]],
    }


def _qr_pose_summary(data: Data) -> dict[str, float]:
    pose = data.get("camera_from_qr") if data.get("found") else None
    x, y, z = (float("nan"),) * 3 if pose is None else (pose[0][3], pose[1][3], pose[2][3])
    return {"found": 0.0 if pose is None else 1.0, "x": x, "y": y, "z": z}


RESULTS = ResultKind(
    ("text", "corners", "camera_from_qr"),
    _qr_pose_expected,
    _qr_pose_summary,
    units={"found": "1 found, 0 not", "x": "m", "y": "m", "z": "m"},
)
"""A QR pose result: text, corners and camera_from_qr (its translation in metres in the
summary)."""
