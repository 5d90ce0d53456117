"""``qr_calibration``: fast calibration from a QR code (the paper's section 2.5, Table 3).

Teaching and execution do the same measurement: from the (taught) view pose, look for the QR
code whose text matches the taught string (INSPECT ``qr_inspection`` on colour frames, up to
``attempts`` captures), capture one colour and ``depth_frames`` depth frames, and ask the
server's ``qr_pose`` inspection for ``camera_from_qr`` (the QR frame of docs/conventions.md,
equations 1-4, with a quality report). Then ``base_from_qr = base_from_camera @
camera_from_qr`` (equation 5; the robot's mount base frame) becomes the calibration of the frame
``frame`` (default ``qr:<the text after its last colon>``, e.g. ``qr:station-1``) in the world
model, and the robot's active base frame (step 10). Records taught relative to that frame (the
switch: ``press``) are then reached wherever the robot docked or the station moved.

Teaching records the view pose (default: where the tool is), the text (default: read from the
code) and the measured ``base_from_qr`` (``taught_base_from_qr``); each execution reports how
far the station moved since (``shift_m``, ``shift_rad``).

Failure reasons: ``not_found`` (no code with that text), ``no_depth`` (a corner or the code has
no depth), ``poor_quality`` (the server judged the measurement poor: plane RMS, valid depth).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry import invert_transform

from ..devices import Camera
from ..vision_geometry import rotation_error_rad
from .base import Args, Skill, SkillContext, SkillSpec, register_skill
from .outcome import FailureReason, Outcome, SkillFailed, fail
from .record import Param, ParamType, TaughtRecord, pose_to_yaml
from .world import BASE_FRAME, Calibration

__all__ = ["QRCalibration", "QRMeasurement", "default_frame_name", "measure_qr_frame"]

FloatArray = NDArray[np.float64]


def default_frame_name(text: str) -> str:
    """``cellvision:station-1`` → ``qr:station-1``."""
    return "qr:" + text.rsplit(":", 1)[-1]


@dataclass(frozen=True, eq=False)
class QRMeasurement:
    """One measurement: ``base_from_qr`` (mount base frame), ``camera_from_qr`` and
    ``base_from_camera`` it came from, the code's ``text``, the server's ``method`` and
    ``quality`` numbers, the number of depth frames and the colour attempts needed, and the
    server's ``warnings`` on the measurement (e.g. the depth disagreeing with the printed side:
    the inspection passes, but the sensor needs its check)."""

    base_from_qr: FloatArray
    camera_from_qr: FloatArray
    base_from_camera: FloatArray
    text: str
    method: str
    quality: dict[str, float]
    depth_frames: int
    attempts: int
    warnings: tuple[str, ...] = ()


def _rigid(value: Any) -> FloatArray | None:
    try:
        mat = np.asarray(value, np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        return None
    rot = mat[:3, :3]
    if (
        not np.all(np.isfinite(mat))
        or not np.allclose(mat[3], [0, 0, 0, 1])
        or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6)
        or np.linalg.det(rot) <= 0
    ):
        return None
    return mat


def _numbers(values: Mapping[str, Any]) -> dict[str, float]:
    return {
        str(k): float(v)
        for k, v in values.items()
        if isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v)
    }


def measure_qr_frame(
    ctx: SkillContext,
    camera: Camera,
    *,
    text: str | None,
    qr_inspection: str | None,
    pose_inspection: str,
    depth_frames: int,
    attempts: int,
) -> QRMeasurement:
    """Table 3, steps 1-9, from where the camera is now. ``text`` None: take the first code
    the colour inspection reads. Ends the skill (``fail``) when it cannot measure."""
    seen: list[str] = []
    used = 0
    if qr_inspection:
        found = None
        for used in range(1, attempts + 1):  # noqa: B007 (used after the loop)
            ctx.report(f"looking for the QR code (attempt {used})", 0.1)
            cap = camera.capture()
            data = dict(ctx.vision.inspect(qr_inspection, cap.color).data)
            read = data.get("text")
            if data.get("found") and isinstance(read, str):
                seen.append(read)
                if text is None or read == text:
                    found = read
                    break
        if found is None:
            what = "a QR code" if text is None else f"the QR code {text!r}"
            fail(
                FailureReason.NOT_FOUND,
                f"{what} not found in {attempts} capture(s)"
                + (f" (read: {', '.join(sorted(set(seen)))})" if seen else ""),
                {"read": seen},
            )
        text = found
    ctx.report(f"measuring with {depth_frames} depth frames", 0.5)
    cap = camera.capture(depth_frames=depth_frames)
    result = ctx.vision.inspect(pose_inspection, cap.color, depth=list(cap.depth))
    data = dict(result.data)
    reason = str(data.get("reason", ""))
    if not data.get("found"):
        code = FailureReason.NO_DEPTH if "depth" in reason.lower() else FailureReason.NOT_FOUND
        fail(code, f"inspection {pose_inspection!r}: {reason or 'no QR code'}", {"reason": reason})
    read = data.get("text")
    if text is not None and read != text:
        fail(
            FailureReason.NOT_FOUND,
            f"inspection {pose_inspection!r} measured the code {read!r}, not {text!r}",
            {"read": read},
        )
    raw_quality = dict(data.get("quality") or {})
    quality = _numbers(raw_quality)
    # the numbers go into the calibration; the server's warnings (strings) would be lost with
    # them, and a sensor that drifted would calibrate silently
    raw_warnings = raw_quality.get("warnings")
    warnings = tuple(
        str(w) for w in (raw_warnings if isinstance(raw_warnings, list) else []) if str(w)
    )
    for warning in warnings:
        ctx.report(f"warning: {warning}", 0.6)
    if not result.passed:
        fail(
            FailureReason.POOR_QUALITY,
            f"inspection {pose_inspection!r}: {reason or 'verdict fail'}",
            {"quality": quality},
        )
    camera_from_qr = _rigid(data.get("camera_from_qr"))
    if camera_from_qr is None:
        fail(
            FailureReason.VISION_ERROR,
            f"inspection {pose_inspection!r} returned no valid camera_from_qr",
        )
    base_from_qr = cap.base_from_camera @ camera_from_qr  # equation 5
    return QRMeasurement(
        base_from_qr=base_from_qr,
        camera_from_qr=camera_from_qr,
        base_from_camera=cap.base_from_camera.copy(),
        text=str(read),
        method=str(data.get("method", "")),
        quality=quality,
        depth_frames=len(cap.depth),
        attempts=max(used, 1),
        warnings=warnings,
    )


@register_skill
class QRCalibration(Skill):
    spec = SkillSpec(
        name="qr_calibration",
        doc="calibrate a station's frame from its QR code: camera_from_qr from colour + depth "
        "(paper, Table 3)",
        params=(
            Param("text", ParamType.STR, "the QR code's text (taught: read from the code)"),
            Param(
                "frame",
                ParamType.STR,
                "the calibrated frame's name (none: qr:<text after its last colon>)",
                default=None,
            ),
            Param(
                "view_pose",
                ParamType.POSE,
                "tool pose (mount base frame) to look at the code from (none: where it is)",
                "m, rad",
                default=None,
            ),
            Param("camera", ParamType.STR, "the robot's RGB-D camera", default="rgbd"),
            Param(
                "qr_inspection",
                ParamType.STR,
                "the server's qr inspection that finds and reads the code (none: skip)",
                default="station_qr",
            ),
            Param(
                "pose_inspection",
                ParamType.STR,
                "the server's qr_pose inspection",
                default="station_pose",
            ),
            Param(
                "depth_frames",
                ParamType.INT,
                "depth frames averaged",
                default=5,
                minimum=1,
                maximum=60,
            ),
            Param(
                "attempts",
                ParamType.INT,
                "colour captures to find the code in",
                default=3,
                minimum=1,
                maximum=100,
            ),
            Param(
                "taught_base_from_qr",
                ParamType.POSE,
                "the code's pose measured when teaching (set by teach)",
                "m, rad",
                default=None,
            ),
        ),
    )

    @staticmethod
    def _frame_name(args: Mapping[str, Any]) -> str:
        frame = args.get("frame")
        return str(frame) if frame else default_frame_name(str(args["text"]))

    def _measure(self, ctx: SkillContext, values: Mapping[str, Any]) -> QRMeasurement:
        view = values.get("view_pose")
        if view is not None:
            ctx.report("moving to the view pose", 0.0)
            ctx.robot.move_linear(view)
        qr_inspection = values.get("qr_inspection")
        return measure_qr_frame(
            ctx,
            ctx.camera(str(values["camera"])),
            text=values.get("text"),
            qr_inspection=str(qr_inspection) if qr_inspection else None,
            pose_inspection=str(values["pose_inspection"]),
            depth_frames=int(values["depth_frames"]),
            attempts=int(values["attempts"]),
        )

    def _calibrate(
        self, ctx: SkillContext, m: QRMeasurement, frame: str, source: str
    ) -> Calibration:
        distance = float(np.linalg.norm(m.camera_from_qr[:3, 3]))
        quality = {**m.quality, "distance_m": distance, "depth_frames": float(m.depth_frames)}
        cal = Calibration(frame, m.base_from_qr, ctx.clock.now(), quality, True, source)
        ctx.world.set_calibration(cal)
        ctx.world.use_frame(frame)  # Table 3, step 10: the robot's base is now the QR frame
        return cal

    def teach(
        self,
        name: str,
        values: Mapping[str, Any],
        ctx: SkillContext,
        *,
        frame: str = BASE_FRAME,
        from_current_pose: bool = False,
        notes: str = "",
    ) -> TaughtRecord:
        """Measure now: the view pose is the current tool pose unless given, the text is read
        from the code unless given; sets the calibration and records ``taught_base_from_qr``."""
        if frame != BASE_FRAME:
            raise ValueError("a QR calibration is taught in the base frame (it makes the frame)")
        given = dict(values)
        ctx.world.use_frame(BASE_FRAME)  # the view pose is in the mount base frame
        view = given.get("view_pose")
        if view is None or (isinstance(view, str) and view == "current"):
            given["view_pose"] = ctx.world.tool_pose_in(BASE_FRAME)
        plain = {
            p.name: p.encode(given[p.name]) if p.name in given else p.encode(p.default)
            for p in self.spec.params
            if p.name in given or not p.required
        }
        typed = {k: self.spec.param(k).decode(v) for k, v in plain.items()}
        try:
            m = self._measure(ctx, typed)
        except SkillFailed as exc:
            raise ValueError(f"teaching {name!r}: {exc.message}") from None
        given["text"] = m.text
        given["taught_base_from_qr"] = m.base_from_qr
        self._calibrate(ctx, m, self._frame_name(given), f"{self.name}/{name} (taught)")
        return super().teach(name, given, ctx, frame=BASE_FRAME, notes=notes)

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        m = self._measure(ctx, dict(args))
        frame = self._frame_name(args)
        cal = self._calibrate(ctx, m, frame, args.record.key)
        data: dict[str, Any] = {
            "frame": frame,
            "text": m.text,
            "method": m.method,
            "base_from_qr": pose_to_yaml(m.base_from_qr),
            "quality": dict(cal.quality),
            "attempts": m.attempts,
        }
        if m.warnings:
            data["warnings"] = list(m.warnings)
        taught = args["taught_base_from_qr"]
        if taught is not None:
            delta = invert_transform(taught) @ m.base_from_qr
            data["shift_m"] = round(float(np.linalg.norm(delta[:3, 3])), 6)
            data["shift_rad"] = round(rotation_error_rad(taught, m.base_from_qr), 6)
        ctx.report(f"calibrated {frame}", 1.0)
        return Outcome.success(data)
