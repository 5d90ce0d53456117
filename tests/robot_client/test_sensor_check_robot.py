"""The robot-driven sensor check in the simulated Grundfos cell, through a real server on
loopback: the RGB-D tool camera, given a known misregistration and depth scale error (as the
bench's calibration section injects them), is turned about the QR code by the robot; the fit
finds them, and says a sensor without them needs no correction. Accuracy, not timing."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from geometry import transform_from_xyz_rpy
from robot_client import SyncVisionClient
from robot_client.commissioning.sensor_check import check_sensor
from robot_client.devices.sim import sim_devices
from simulation import SimCell, load_scene

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"
# The scene's "view QR" pose: the RGB-D camera about 1 m from the station's code.
VIEW_QR = transform_from_xyz_rpy([0.25, -0.36, 0.35], [-1.5707963, 0.0, -1.5707963])
CORNER_BIAS_PX = -0.035  # the detector's bias on the sim's camera (bench calibration measures it)


@pytest.fixture(scope="module")
def vision(
    tmp_path_factory: pytest.TempPathFactory, cell_config: Any, live_server: Any
) -> Iterator[SyncVisionClient]:
    tmp = tmp_path_factory.mktemp("sensor-check-server")
    with (
        live_server(cell_config(tmp, tmp / "world.json")) as port,
        SyncVisionClient("127.0.0.1", port, request_timeout_s=30.0) as client,
    ):
        yield client


def cell_with_sensor(shift_px: tuple[float, float], scale_bias: float, seed: int) -> SimCell:
    scene = load_scene(SCENE)
    cameras = []
    for camera in scene.cameras:
        if camera.name == "rgbd":
            assert camera.depth is not None
            depth = dataclasses.replace(
                camera.depth, misregistration_px=shift_px, scale_bias=scale_bias
            )
            camera = dataclasses.replace(camera, depth=depth)
        cameras.append(camera)
    return SimCell(dataclasses.replace(scene, cameras=tuple(cameras)), seed=seed)


def run_check(vision: SyncVisionClient, cell: SimCell) -> Any:
    devices = sim_devices(cell, vision=vision)
    devices.robot.move_linear(VIEW_QR)
    check = check_sensor(
        devices, camera="rgbd", inspection="station_pose", corner_bias_px=CORNER_BIAS_PX
    )
    assert check.skipped == []
    assert len(check.views) == 12
    assert devices.robot.base_from_tool() == pytest.approx(VIEW_QR)  # back at the start
    return check


def test_a_misregistered_sensor_is_measured_and_told_to_be_corrected(
    vision: SyncVisionClient,
) -> None:
    check = run_check(vision, cell_with_sensor((2.0, 1.0), -0.01, seed=0))
    reg = check.registration
    assert reg.scale == pytest.approx(0.99, abs=0.002)
    assert reg.shift_px[0] == pytest.approx(2.0, abs=0.6)
    assert reg.shift_px[1] == pytest.approx(1.0, abs=0.6)
    assert not check.ok
    assert f"depth scale {reg.scale:.4f}" in check.advice
    assert "set the qr_pose inspection's depth_scale" in check.advice


def test_a_good_sensor_needs_no_correction(vision: SyncVisionClient) -> None:
    check = run_check(vision, cell_with_sensor((0.0, 0.0), 0.0, seed=1))
    assert check.registration.scale == pytest.approx(1.0, abs=0.002)
    assert check.ok, check.advice


def test_a_camera_without_depth_or_off_the_tool_is_refused(vision: SyncVisionClient) -> None:
    devices = sim_devices(cell_with_sensor((0.0, 0.0), 0.0, seed=0), vision=vision)
    with pytest.raises(ValueError, match="'qc_camera' is not on the tool"):
        check_sensor(devices, camera="qc_camera", inspection="station_pose")
    with pytest.raises(ValueError, match="'tool_camera' has no depth sensor"):
        check_sensor(devices, camera="tool_camera", inspection="station_pose")
    # At home the RGB-D camera looks down at the conveyor, not at the code.
    with pytest.raises(ValueError, match="the QR code is not in view of camera 'rgbd'"):
        check_sensor(devices, camera="rgbd", inspection="station_pose")
