"""The robot's world model: what skills' pre- and post-conditions are checked against.

It holds what the robot believes (the name of the part it holds, calibrated frames and their
quality, free-form facts) and reads what it can sense (the gripper's ``holding``, the robot's
pose) from the devices on demand, so it never goes stale.

Frames: a calibrated frame is named (``"qr:station-1"``) and stored as ``base_from_frame`` in
the robot's mount base frame; ``"base"`` is the mount itself and always valid.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import invert_transform

from ..devices import Clock, Devices
from .outcome import FailureReason
from .record import pose_from_yaml, pose_to_yaml, utc_now_iso

__all__ = ["BASE_FRAME", "Calibration", "CalibrationProblem", "WorldModel"]

FloatArray = NDArray[np.float64]
BASE_FRAME = "base"


@dataclass(frozen=True, eq=False)
class Calibration:
    """A calibrated frame: ``base_from_frame`` (mount base frame, metres), when it was made
    (``time_s`` on the skills' clock; ``taught_at`` wall time, UTC ISO), its ``quality``
    (numbers the calibration skill reports, e.g. ``{"residual_m": 0.0004}``), whether the
    calibration skill judged it ``valid``, and which record made it (``source``)."""

    frame: str
    base_from_frame: FloatArray
    time_s: float
    quality: Mapping[str, float] = field(default_factory=dict)
    valid: bool = True
    source: str = ""
    taught_at: str = field(default_factory=utc_now_iso)

    def to_dict(self) -> dict[str, Any]:
        return {
            "frame": self.frame,
            "base_from_frame": pose_to_yaml(self.base_from_frame),
            "time_s": self.time_s,
            "quality": {k: float(v) for k, v in self.quality.items()},
            "valid": self.valid,
            "source": self.source,
            "taught_at": self.taught_at,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Calibration:
        return cls(
            frame=str(data["frame"]),
            base_from_frame=pose_from_yaml(data["base_from_frame"], "base_from_frame"),
            time_s=float(data["time_s"]),
            quality={str(k): float(v) for k, v in dict(data.get("quality") or {}).items()},
            valid=bool(data.get("valid", True)),
            source=str(data.get("source", "")),
            taught_at=str(data.get("taught_at", "")),
        )


@dataclass(frozen=True)
class CalibrationProblem:
    """Why a frame cannot be used: a reason code and a sentence."""

    reason: FailureReason
    message: str


class WorldModel:
    """What skills know about the cell. ``calibration_max_age_s``: a calibration older than
    this (on ``clock``) is stale; None: calibrations do not age (they are invalidated by
    :meth:`invalidate_calibrations`, e.g. when the mobile robot docks again)."""

    def __init__(
        self,
        devices: Devices,
        *,
        clock: Clock | None = None,
        calibration_max_age_s: float | None = None,
    ) -> None:
        self.devices = devices
        self.clock: Clock = clock or devices.clock
        self.calibration_max_age_s = calibration_max_age_s
        self.held_part: str | None = None
        self.calibrations: dict[str, Calibration] = {}
        self.facts: dict[str, Any] = {}

    # --- what is sensed -----------------------------------------------------------------
    @property
    def holding(self) -> bool:
        """Whether the gripper holds something (asked from the gripper each time)."""
        return bool(self.devices.gripper.holding)

    def mount_from_tool(self) -> FloatArray:
        """The tool pose in the robot's mount base frame, whatever frame is active."""
        robot = self.devices.robot
        pose: FloatArray = robot.base_frame() @ robot.base_from_tool()
        return pose

    def tool_pose_in(self, frame: str) -> FloatArray:
        """``frame_from_tool``: the tool pose in a named frame (ValueError if not calibrated)."""
        result: FloatArray = invert_transform(self.base_from_frame(frame)) @ self.mount_from_tool()
        return result

    # --- calibrations -------------------------------------------------------------------
    def set_calibration(self, calibration: Calibration) -> None:
        self.calibrations[calibration.frame] = calibration

    def invalidate_calibrations(self, reason: str = "the robot moved to another station") -> None:
        """Mark every calibration invalid (they stay listed, with why)."""
        for name, cal in list(self.calibrations.items()):
            self.calibrations[name] = Calibration(
                cal.frame,
                cal.base_from_frame,
                cal.time_s,
                {**cal.quality},
                False,
                f"{cal.source} (invalidated: {reason})",
                cal.taught_at,
            )

    def calibration_problem(self, frame: str) -> CalibrationProblem | None:
        """None if ``frame`` can be used now, else why not."""
        if frame == BASE_FRAME:
            return None
        cal = self.calibrations.get(frame)
        if cal is None:
            known = ", ".join(sorted(self.calibrations)) or "none"
            return CalibrationProblem(
                FailureReason.NO_CALIBRATION,
                f"frame {frame!r} has not been calibrated (calibrated frames: {known}); "
                f"run its calibration skill first",
            )
        if not cal.valid:
            return CalibrationProblem(
                FailureReason.CALIBRATION_INVALID,
                f"the calibration of {frame!r} is not valid ({cal.source or 'no source'}; "
                f"quality {dict(cal.quality)})",
            )
        if self.calibration_max_age_s is not None:
            age = self.clock.now() - cal.time_s
            if age > self.calibration_max_age_s:
                return CalibrationProblem(
                    FailureReason.CALIBRATION_STALE,
                    f"the calibration of {frame!r} is {age:.1f} s old, more than the "
                    f"{self.calibration_max_age_s:g} s allowed",
                )
        return None

    def base_from_frame(self, frame: str) -> FloatArray:
        """The named frame in the mount base frame (ValueError if it cannot be used)."""
        if frame == BASE_FRAME:
            return np.eye(4)
        problem = self.calibration_problem(frame)
        if problem is not None:
            raise ValueError(problem.message)
        return self.calibrations[frame].base_from_frame.copy()

    def use_frame(self, frame: str) -> None:
        """Make ``frame`` the robot's active base frame (the paper's "set the robot's base")."""
        self.devices.robot.set_base_frame(self.base_from_frame(frame))
        self.facts["active_frame"] = frame

    # --- persistence (the CLI keeps calibrations between runs) ---------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "held_part": self.held_part,
            "calibrations": [c.to_dict() for c in self.calibrations.values()],
        }

    def load_dict(self, data: Mapping[str, Any]) -> None:
        held = data.get("held_part")
        self.held_part = None if held is None else str(held)
        self.calibrations = {}
        for item in data.get("calibrations") or []:
            self.set_calibration(Calibration.from_dict(item))


def distance_to_polyline(p: ArrayLike, points: list[FloatArray]) -> float:
    """Distance (metres) from ``p`` (3,) to the polyline through ``points`` (one point: to it)."""
    q = np.asarray(p, np.float64)
    if len(points) == 1:
        return float(np.linalg.norm(q - points[0]))
    best = np.inf
    for a, b in zip(points[:-1], points[1:], strict=True):
        ab = b - a
        denom = float(ab @ ab)
        t = 0.0 if denom == 0 else float(np.clip((q - a) @ ab / denom, 0.0, 1.0))
        best = min(best, float(np.linalg.norm(q - (a + t * ab))))
    return best
