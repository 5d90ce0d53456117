"""Hand-eye calibrations in the teach store (robot_client.skills.camera_mounts): the record
round trip, what a calibrated camera's captures say, and bad records named."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from geometry import CameraIntrinsics, make_transform, rotation_from_rpy
from robot_client.devices.sim import SimCamera, sim_devices
from robot_client.skills import SkillContext, SkillFailed
from robot_client.skills.camera_mounts import (
    CalibratedCamera,
    hand_eye_record,
    stored_hand_eye,
)
from robot_client.teach_store import TeachStore
from simulation import SimCell

SCENE = Path(__file__).resolve().parents[2] / "examples" / "scenes" / "grundfos_cell.yaml"
CALIBRATED = make_transform(rotation_from_rpy(0.001, -0.002, 0.003), [0.0702, 0.0003, -0.0999])
SOLVED = CameraIntrinsics(1024, 768, 1399.2, 1399.6, 511.8, 383.1, (-0.08, 0.05, 0.0, 0.0, 0.0))


def _store(tmp_path: Path, **params: object) -> TeachStore:
    store = TeachStore(tmp_path / "taught.yaml")
    record = hand_eye_record(
        "tool_camera",
        "eye_in_hand",
        CALIBRATED,
        intrinsics=SOLVED,
        verdict="good",
        reasons=("reprojection RMS 0.18 px over 15 views",),
        figures={"rms_px": 0.18},
    )
    store.put(replace(record, params={**record.params, **params}))
    return store


def test_a_stored_calibration_reads_back(tmp_path: Path) -> None:
    store = _store(tmp_path)
    stored = stored_hand_eye(store.records(), "tool_camera")
    assert stored is not None
    assert stored.setup == "eye_in_hand"
    np.testing.assert_allclose(stored.pose, CALIBRATED, atol=1e-9)
    assert stored.intrinsics == SOLVED
    assert stored.verdict == "good"
    assert stored_hand_eye(store.records(), "rgbd") is None
    text = store.path.read_text(encoding="utf-8")
    assert "tool_from_camera:" in text
    assert "good: reprojection RMS 0.18 px over 15 views" in text


def test_skills_see_the_calibrated_mount_and_intrinsics(tmp_path: Path) -> None:
    cell = SimCell.from_yaml(SCENE)
    devices = sim_devices(cell)
    nominal = make_transform(np.eye(3), [0.075, 0.0, -0.1])
    devices.cameras["tool_camera"] = SimCamera(cell, "tool_camera", nominal_mount=nominal)
    ctx = SkillContext.create(devices, store=_store(tmp_path))
    camera = ctx.camera("tool_camera")
    assert isinstance(camera, CalibratedCamera)
    assert camera.intrinsics == SOLVED
    tool_from_camera = camera.tool_from_camera
    assert tool_from_camera is not None
    np.testing.assert_allclose(tool_from_camera, CALIBRATED, atol=1e-9)
    capture = camera.capture()
    expected = devices.robot.base_from_tool() @ CALIBRATED
    np.testing.assert_allclose(capture.base_from_camera, expected, atol=1e-9)
    assert capture.intrinsics == SOLVED
    assert camera.has_depth is False  # the device's other attributes pass through
    # Without a store, or without a record for it, a camera is the device's own.
    assert SkillContext.create(devices).camera("tool_camera") is devices.cameras["tool_camera"]
    assert ctx.camera("rgbd") is devices.cameras["rgbd"]


def test_a_bad_record_fails_the_skill_naming_the_key(tmp_path: Path) -> None:
    store = _store(tmp_path, tool_from_camera={"xyz": [0.07, 0.0], "rpy": [0.0, 0.0, 0.0]})
    ctx = SkillContext.create(sim_devices(SimCell.from_yaml(SCENE)), store=store)
    with pytest.raises(SkillFailed, match=r"hand_eye/tool_camera: tool_from_camera\.xyz"):
        ctx.camera("tool_camera")


def test_a_tool_calibration_on_a_fixed_camera_is_refused(tmp_path: Path) -> None:
    store = TeachStore(tmp_path / "taught.yaml")
    record = hand_eye_record(
        "qc_camera",
        "eye_in_hand",
        CALIBRATED,
        intrinsics=SOLVED,
        verdict="good",
        reasons=(),
        figures={},
    )
    store.put(record)
    ctx = SkillContext.create(sim_devices(SimCell.from_yaml(SCENE)), store=store)
    with pytest.raises(SkillFailed, match="calibrated on the tool, but the camera is a fixed"):
        ctx.camera("qc_camera")
