"""The device cameras against the real vendor SDKs, where they are installed (skipped
elsewhere; the project's test extras install neither).

Without a device these check that the SDK's API is the one the backends and the fakes assume
(the no-device answers). On a cell PC with a device they are a hardware smoke test: one frame
of the configured kind. GenICam needs a GenTL producer: ``CELLVISION_GENTL_CTI=/path/x.cti``.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from protocol import CameraUnavailable
from vision_server.cameras import (
    GenICamCamera,
    GenICamCameraSettings,
    RealSenseCamera,
    RealSenseCameraSettings,
)


def test_realsense_with_the_real_pyrealsense2() -> None:
    rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 (the realsense extra)")
    devices = len(rs.context().query_devices())
    with RealSenseCamera("rgbd", RealSenseCameraSettings()) as cam:
        if devices == 0:
            with pytest.raises(CameraUnavailable, match="no RealSense device is connected"):
                cam.grab(timeout_s=2.0)
            return
        if devices > 1:
            pytest.skip("several RealSense devices: this smoke test takes the only one")
        frame = cam.grab(timeout_s=5.0)
        assert frame.color.shape == (480, 640, 3)
        assert frame.depth is not None
        assert frame.depth.shape == (480, 640)
        assert cam.intrinsics is not None
        assert cam.intrinsics.width == 640


def test_genicam_with_the_real_harvesters(tmp_path: Path) -> None:
    pytest.importorskip("harvesters.core", reason="harvesters (the genicam extra)")
    producer = os.environ.get("CELLVISION_GENTL_CTI")
    if producer is None:
        # No producer: one that loads nothing must say so, naming it.
        (tmp_path / "none.cti").write_bytes(b"not a GenTL producer")
        with (
            GenICamCamera("qc", GenICamCameraSettings(Path("none.cti")), base_dir=tmp_path) as cam,
            pytest.raises(CameraUnavailable, match="no GenICam device is visible through none.cti"),
        ):
            cam.grab(timeout_s=2.0)
        return
    with GenICamCamera("qc", GenICamCameraSettings(Path(producer))) as cam:
        frame = cam.grab(timeout_s=5.0)
        assert frame.color.ndim == 2
        assert frame.color.size > 0
