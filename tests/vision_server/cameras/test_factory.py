"""make_camera, the request source, CameraFrame checks and the package's public API."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import vision_server.cameras as cameras
from protocol import InvalidArgument
from vision_server.cameras import (
    CameraFrame,
    FolderCamera,
    FolderCameraSettings,
    Intrinsics,
    RequestCamera,
    RequestCameraSettings,
    make_camera,
)


def test_public_api_is_importable() -> None:
    for name in cameras.__all__:
        assert hasattr(cameras, name), name


def test_request_camera_cannot_grab() -> None:
    intrinsics = Intrinsics(1024, 768, 1400.0, 1400.0, 511.5, 383.5)
    camera = make_camera(
        "tool", RequestCameraSettings(intrinsics=intrinsics, depth=True), base_dir=Path(".")
    )
    assert isinstance(camera, RequestCamera)
    assert camera.source == "request"
    assert camera.has_depth
    with camera:
        with pytest.raises(InvalidArgument, match="'tool' gets its images from the request"):
            camera.grab(timeout_s=1.0)
        with pytest.raises(InvalidArgument):
            camera.grab_many(3, timeout_s=1.0)
    assert camera.descriptor() == {
        "name": "tool",
        "source": "request",
        "depth": True,
        "intrinsics": intrinsics.to_dict(),
    }
    assert camera.status()["connected"] is False


def test_relative_folder_resolves_against_base_dir(tmp_path: Path) -> None:
    camera = make_camera("f", FolderCameraSettings(Path("imgs")), base_dir=tmp_path)
    assert isinstance(camera, FolderCamera)
    assert camera.root == tmp_path / "imgs"


def test_make_camera_rejects_bad_names_and_settings(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="name"):
        make_camera("", RequestCameraSettings(), base_dir=tmp_path)
    with pytest.raises(TypeError, match="unknown settings"):
        make_camera("x", object(), base_dir=tmp_path)  # type: ignore[arg-type]


def test_grab_many_counts_must_be_positive(tmp_path: Path) -> None:
    camera = make_camera("f", FolderCameraSettings(tmp_path), base_dir=tmp_path)
    with pytest.raises(InvalidArgument, match=">= 1"):
        camera.grab_many(0, timeout_s=1.0)


def test_camera_frame_checks_its_arrays() -> None:
    color = np.zeros((4, 6, 3), np.uint8)
    frame = CameraFrame(color, np.zeros((4, 6), np.uint16), 0.0, 0)
    assert (frame.width, frame.height) == (6, 4)
    assert not frame.color.flags.writeable
    with pytest.raises(ValueError, match="color"):
        CameraFrame(np.zeros((4, 6), np.float32), None, 0.0, 0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="depth"):
        CameraFrame(np.zeros((4, 6), np.uint8), np.zeros((4, 5), np.uint16), 0.0, 0)
