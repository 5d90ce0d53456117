"""qr_calibration (paper Table 3): teach, execute after the robot docked elsewhere, press the
switch taught in the QR frame; with a ground-truth "server" first, then end to end against a
real server (accuracy of the corner and the plane method side by side)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from geometry import (
    invert_transform,
    make_transform,
    rotation_from_rpy,
    transform_from_xyz_rpy,
    transform_points,
)
from robot_client.devices import Capture
from robot_client.devices.sim import SimCamera, sim_devices
from robot_client.skills import FailureReason, SkillContext, default_registry, execute
from robot_client.skills.qr_calibration import default_frame_name
from robot_client.vision_geometry import rotation_error_rad
from simulation import GroundTruth, SimCell

SCENE = Path(__file__).resolve().parents[2] / "examples/scenes/grundfos_cell.yaml"
REG = default_registry()
FloatArray = NDArray[np.float64]
TEXT = "cellvision:station-1"
FRAME = "qr:station-1"
VIEW = transform_from_xyz_rpy([0.25, -0.36, 0.35], [-np.pi / 2, 0.0, -np.pi / 2])


def true_base_from_qr(cell: SimCell) -> FloatArray:
    world_from_qr = cell.render("rgbd").truth.qr_codes["qr_station"].world_from_qr
    result: FloatArray = invert_transform(cell.robot.world_from_base) @ world_from_qr
    return result


def switch_world(cell: SimCell) -> FloatArray:
    p: FloatArray = cell.scene.switches[0].world_from_switch[:3, 3].copy()
    return p


class TruthCamera(SimCamera):
    """A sim camera that remembers the ground truth of its last frame."""

    last: GroundTruth | None = None

    def capture(self, *, depth_frames: int = 0) -> Capture:
        pose = self._base_from_camera()
        frames = [self.cell.render(self.name) for _ in range(max(1, depth_frames))]
        self.last = frames[0].truth
        depth = tuple(f.depth for f in frames if f.depth is not None)[:depth_frames]
        return Capture(
            frames[0].color, depth, self.intrinsics, pose, self.cell.robot.base_from_user, self.name
        )


class TruthQRVision:
    """station_qr / station_pose answered from the ground truth of the camera's last frame;
    ``pose_data`` overrides what station_pose returns."""

    def __init__(self, camera: TruthCamera) -> None:
        self.camera = camera
        self.pose_data: dict[str, Any] | None = None
        self.passed = True
        self.requests: list[tuple[str, int]] = []

    def inspect(self, inspection: str, image: Any = None, **kwargs: Any) -> Any:
        depth = list(kwargs.get("depth", ()))
        self.requests.append((inspection, len(depth)))
        truth = self.camera.last
        assert truth is not None
        q = truth.qr_codes["qr_station"]
        if not q.visible:
            return SimpleNamespace(passed=False, data={"found": False, "reason": "no QR code"})
        if inspection == "station_qr":
            data = {"found": True, "text": q.text, "corners": q.corners_uv.tolist()}
            return SimpleNamespace(passed=True, data=data)
        data = self.pose_data or {
            "found": True,
            "text": q.text,
            "method": "plane",
            "camera_from_qr": q.camera_from_qr.tolist(),
            "quality": {"plane_rms_m": 0.0012, "valid_depth_fraction": 0.99},
        }
        return SimpleNamespace(passed=self.passed, data=data)

    def ping(self, data: str = "") -> float:
        return 0.0

    def list_inspections(self) -> tuple[dict[str, Any], ...]:
        return ()

    def capture(self, camera: str, **kwargs: Any) -> Any:
        raise NotImplementedError


def truth_ctx(seed: int = 7) -> tuple[SkillContext, SimCell, TruthQRVision]:
    cell = SimCell.from_yaml(SCENE, seed=seed)
    devices = sim_devices(cell)
    camera = TruthCamera(cell, "rgbd")
    devices.cameras["rgbd"] = camera
    vision = TruthQRVision(camera)
    devices.vision = vision
    return SkillContext.create(devices), cell, vision


def touch_pose_in_qr(base_from_qr: FloatArray, cell: SimCell) -> FloatArray:
    """The switch's touch pose taught in the QR frame (tool z = the QR's z, into the panel),
    as an operator jogging the robot onto the switch would record it."""
    p_base = transform_points(invert_transform(cell.robot.world_from_base), switch_world(cell))
    p_qr = transform_points(invert_transform(base_from_qr), p_base).reshape(3)
    return make_transform(np.eye(3), p_qr)


def pressed_error(ctx: SkillContext, cell: SimCell, approach_m: float) -> float:
    """After press retracted: where the touch pose really was vs the true switch (metres)."""
    world_from_touch = cell.world.world_from_tool() @ make_transform(np.eye(3), [0, 0, approach_m])
    return float(np.linalg.norm(world_from_touch[:3, 3] - switch_world(cell)))


def test_default_frame_name() -> None:
    assert default_frame_name(TEXT) == FRAME
    assert default_frame_name("plain") == "qr:plain"


def test_teach_reads_the_code_records_the_view_and_calibrates() -> None:
    ctx, cell, vision = truth_ctx()
    ctx.robot.move_linear(VIEW)
    skill = REG.get("qr_calibration")
    record = skill.teach("station", {}, ctx)
    assert record.params["text"] == TEXT
    assert record.frame == "base"
    assert np.allclose(skill.spec.param("view_pose").decode(record.params["view_pose"]), VIEW)
    cal = ctx.world.calibrations[FRAME]
    assert cal.valid
    assert np.allclose(cal.base_from_frame, true_base_from_qr(cell), atol=1e-6)
    assert cal.quality["distance_m"] == pytest.approx(1.0, abs=0.1)
    assert cal.quality["depth_frames"] == 5
    assert ("station_qr", 0) in vision.requests
    assert ("station_pose", 5) in vision.requests


def test_calibration_after_docking_lets_press_reach_the_switch() -> None:
    ctx, cell, _ = truth_ctx()
    ctx.robot.move_linear(VIEW)
    calib = REG.get("qr_calibration")
    record = calib.teach("station", {"text": TEXT, "depth_frames": 3}, ctx)
    press = REG.get("press")
    touch = touch_pose_in_qr(ctx.world.calibrations[FRAME].base_from_frame, cell)
    press_record = press.teach("switch", {"pose": touch, "depth_m": 0.0}, ctx, frame=FRAME)

    nominal = cell.robot.world_from_base
    docked = cell.dock()
    moved = np.linalg.norm(docked[:3, 3] - nominal[:3, 3])
    assert moved > 0.005  # the robot really arrived somewhere else

    ctx.world.use_frame("base")
    ctx.robot.move_linear(VIEW)  # the taught view pose (base), now looking from elsewhere
    ctx.world.invalidate_calibrations("docked")
    assert execute(press, press_record, ctx).reason is FailureReason.CALIBRATION_INVALID

    outcome = execute(calib, record, ctx)
    assert outcome.ok, outcome
    assert outcome.data["frame"] == FRAME
    assert outcome.data["shift_m"] == pytest.approx(moved, abs=0.02)
    assert outcome.data["shift_m"] > 0.005
    assert np.allclose(
        ctx.world.calibrations[FRAME].base_from_frame, true_base_from_qr(cell), atol=1e-6
    )
    assert np.allclose(ctx.robot.base_frame(), ctx.world.calibrations[FRAME].base_from_frame)
    outcome = execute(press, press_record, ctx)
    assert outcome.ok, outcome
    assert pressed_error(ctx, cell, 0.05) < 1e-6


def test_wrong_text_is_not_found_after_the_attempts() -> None:
    ctx, _, vision = truth_ctx()
    skill = REG.get("qr_calibration")
    record = skill.teach("other", {"text": "cellvision:station-1", "view_pose": VIEW}, ctx)
    other = type(record)(
        record.skill, record.name, {**record.params, "text": "cellvision:station-9"}, "base"
    )
    vision.requests.clear()
    outcome = execute(skill, other, ctx)
    assert outcome.reason is FailureReason.NOT_FOUND
    assert "station-9" in outcome.message
    assert "station-1" in outcome.message  # what it read instead
    assert [r[0] for r in vision.requests] == ["station_qr"] * 3


def test_teach_fails_clearly_when_the_code_is_not_in_view() -> None:
    ctx, _, _ = truth_ctx()
    ctx.robot.move_linear(transform_from_xyz_rpy([0.3, -0.3, 0.4], [np.pi, 0.0, 0.0]))
    skill = REG.get("qr_calibration")
    with pytest.raises(ValueError, match="not found"):
        skill.teach("station", {}, ctx)
    assert FRAME not in ctx.world.calibrations


@pytest.mark.parametrize(
    ("data", "passed", "reason"),
    [
        ({"found": False, "reason": "corner c2 has no depth"}, False, FailureReason.NO_DEPTH),
        ({"found": False, "reason": "no QR code found"}, False, FailureReason.NOT_FOUND),
        (
            {"found": True, "text": TEXT, "camera_from_qr": np.eye(4).tolist(), "reason": "rms"},
            False,
            FailureReason.POOR_QUALITY,
        ),
        ({"found": True, "text": TEXT, "camera_from_qr": [[2.0] * 4] * 4}, True, "vision_error"),
        ({"found": True, "text": "other", "camera_from_qr": np.eye(4).tolist()}, True, "not_found"),
    ],
)
def test_bad_measurements_fail_with_a_reason(
    data: dict[str, Any], passed: bool, reason: FailureReason | str
) -> None:
    ctx, _, vision = truth_ctx()
    skill = REG.get("qr_calibration")
    record = skill.teach("station", {"view_pose": VIEW}, ctx)
    ctx.world.calibrations.clear()
    vision.pose_data, vision.passed = data, passed
    outcome = execute(skill, record, ctx)
    assert outcome.reason == reason
    assert FRAME not in ctx.world.calibrations


def test_rotation_error_rad() -> None:
    a = rotation_from_rpy(0.1, 0.2, 0.3)
    b = a @ rotation_from_rpy(0.0, 0.0, 0.01)
    assert rotation_error_rad(a, b) == pytest.approx(0.01)
    assert rotation_error_rad(a, a) == pytest.approx(0.0, abs=1e-7)
