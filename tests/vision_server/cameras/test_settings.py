"""Camera settings validate on construction, with errors that name the field."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from geometry import CameraIntrinsics
from vision_server.cameras import (
    SOURCE_NAMES,
    AravisCameraSettings,
    FolderCameraSettings,
    GenICamCameraSettings,
    Intrinsics,
    OpenCVCameraSettings,
    RealSenseCameraSettings,
    RecordingCameraSettings,
    RequestCameraSettings,
    SimCameraSettings,
)

K = {"width": 640, "height": 480, "fx": 570.0, "fy": 571.0, "cx": 319.5, "cy": 239.5}


def test_intrinsics_to_dict_is_json_and_round_trips_geometry() -> None:
    intrinsics = Intrinsics(**K, distortion=(0.1, -0.2, 0.001, 0.002, 0.05))
    doc = json.loads(json.dumps(intrinsics.to_dict()))
    assert doc == {**K, "dist": [0.1, -0.2, 0.001, 0.002, 0.05]}  # SPEC §6.4's name
    geometric = intrinsics.to_geometry()
    assert isinstance(geometric, CameraIntrinsics)
    assert geometric.dist == (0.1, -0.2, 0.001, 0.002, 0.05)
    assert Intrinsics.from_geometry(geometric) == intrinsics


def test_intrinsics_distortion_lengths() -> None:
    assert Intrinsics(**K, distortion=[0.1, 0.0, 0.0, 0.0]).distortion == (0.1, 0, 0, 0, 0)
    eight = Intrinsics(**K, distortion=(0.1, 0, 0, 0, 0, 0.3, 0, 0))
    with pytest.raises(ValueError, match="beyond k3"):
        eight.to_geometry()
    assert Intrinsics(**K, distortion=(0.1, 0, 0, 0, 0, 0, 0, 0)).to_geometry().dist[0] == 0.1
    with pytest.raises(ValueError, match="4, 5, 8, 12 or 14"):
        Intrinsics(**K, distortion=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"distortion\[1\]"):
        Intrinsics(**K, distortion=(0.0, float("nan"), 0.0, 0.0))
    with pytest.raises(ValueError, match="distortion must be a list"):
        Intrinsics(**K, distortion="0 0 0 0")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("width", 0),
        ("width", True),
        ("height", 4.5),
        ("fx", -1.0),
        ("fy", float("inf")),
        ("cx", "centre"),
    ],
)
def test_bad_intrinsics_name_the_field(field: str, value: Any) -> None:
    with pytest.raises(ValueError, match=field):
        Intrinsics(**{**K, field: value})


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"device": -1}, "device"),
        ({"device": ""}, "device"),
        ({"device": 1.5}, "device"),
        ({"device": 0, "width": 0}, "width"),
        ({"device": 0, "fps": 0}, "fps"),
        ({"device": 0, "backend": "dshow"}, "backend"),
        ({"device": 0, "reconnect_interval_s": 0}, "reconnect_interval_s"),
        ({"device": 0, "read_timeout_s": -1}, "read_timeout_s"),
        ({"device": 0, "fourcc": "MJPEG"}, "fourcc"),
        ({"device": 0, "loop_file": "yes"}, "loop_file"),
        ({"device": 0, "intrinsics": {"fx": 1}}, "intrinsics"),
        ({"device": 0, "width": 320, "intrinsics": Intrinsics(**K)}, "width"),
    ],
)
def test_bad_opencv_settings_name_the_field(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        OpenCVCameraSettings(**kwargs)


def test_good_opencv_settings() -> None:
    settings = OpenCVCameraSettings(
        "/dev/video0", width=640, height=480, fps=30, backend="v4l2", fourcc="MJPG",
        intrinsics=Intrinsics(**K),
    )  # fmt: skip
    assert settings.fps == 30.0
    assert isinstance(settings.fps, float)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"path": ""}, "path"),
        ({"path": 3}, "path"),
        ({"path": "imgs", "glob": "../*.png"}, "glob"),
        ({"path": "imgs", "glob": "/etc/*"}, "glob"),
        ({"path": "imgs", "depth_glob": "a/../../b.png"}, "depth_glob"),
        ({"path": "imgs", "mode": "loop"}, "mode"),
        ({"path": "imgs", "color": "rgb"}, "color"),
    ],
)
def test_bad_folder_settings_name_the_field(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        FolderCameraSettings(**kwargs)


def test_folder_and_sim_paths_become_paths() -> None:
    assert FolderCameraSettings("imgs").path == Path("imgs")  # type: ignore[arg-type]
    sim = SimCameraSettings("scene.yaml", "cam", state_file="w.json")  # type: ignore[arg-type]
    assert sim.scene == Path("scene.yaml")
    assert sim.state_file == Path("w.json")


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"scene": "s.yaml", "camera": ""}, "camera"),
        ({"scene": "s.yaml", "camera": "c", "seed": -1}, "seed"),
        ({"scene": "s.yaml", "camera": "c", "seed": True}, "seed"),
        ({"scene": "s.yaml", "camera": "c", "state_file": 7}, "state_file"),
    ],
)
def test_bad_sim_settings_name_the_field(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        SimCameraSettings(**kwargs)


def test_request_settings_and_source_names() -> None:
    with pytest.raises(ValueError, match="depth"):
        RequestCameraSettings(depth=1)  # type: ignore[arg-type]
    assert dict(SOURCE_NAMES) == {
        "request": RequestCameraSettings,
        "opencv": OpenCVCameraSettings,
        "folder": FolderCameraSettings,
        "sim": SimCameraSettings,
        "realsense": RealSenseCameraSettings,
        "genicam": GenICamCameraSettings,
        "aravis": AravisCameraSettings,
        "recording": RecordingCameraSettings,
    }


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"serial": "1", "address": "10.0.0.2"}, "at most one of serial, device_id and address"),
        ({"address": "camera-1"}, "address must be the device's IPv4 address"),
        ({"pixel_format": "YUV422"}, "pixel_format must be one of"),
        ({"region": [0, 0, 64]}, "region must be [x, y, width, height]"),
        ({"region": [-1, 0, 64, 64]}, "region must be [x, y, width, height]"),
        ({"packet_size": 100}, "packet_size must be 576 to 65536 bytes"),
        ({"buffers": 0}, "buffers must be a positive integer"),
        ({"buffers": 100}, "buffers must be 1 to 64"),
        ({"trigger_source": "Line1"}, "trigger_source is only used with trigger: hardware"),
        (
            {
                "region": [0, 0, 64, 48],
                "intrinsics": {"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 640, "height": 480},
            },
            "intrinsics are for 640x480 but the camera is set to 64x48",
        ),
    ],
)
def test_aravis_settings_are_checked(kw: dict[str, object], message: str) -> None:
    if isinstance(kw.get("intrinsics"), dict):
        kw = {**kw, "intrinsics": Intrinsics(**kw["intrinsics"])}  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=re.escape(message)):
        AravisCameraSettings(**kw)  # type: ignore[arg-type]


def test_aravis_settings_defaults() -> None:
    s = AravisCameraSettings(trigger="hardware", region=[8, 4, 64, 48])  # type: ignore[arg-type]
    assert s.trigger_source == "Line0"
    assert s.region == (8, 4, 64, 48)
    assert s.packet_size is None
    assert s.packet_resend is True


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"serial": 123456789012}, "serial must be a non-empty string (quote a numeric serial"),
        ({"serial": " "}, "serial must be a non-empty string"),
        ({"fps": 0}, "fps must be a positive integer"),
        ({"width": 640.5, "height": 480}, "width must be a positive integer"),
        ({"width": 640}, "give both width and height, or neither"),
        ({"depth_width": 320}, "give both depth_width and depth_height"),
        ({"depth": "yes"}, "depth must be true or false"),
        ({"reconnect_interval_s": 0}, "reconnect_interval_s must be > 0"),
        (
            {"intrinsics": Intrinsics(**K)},  # 640x480 intrinsics, default 640x480: fine ...
            None,
        ),
        (
            {"width": 1280, "height": 720, "intrinsics": Intrinsics(**K)},
            "intrinsics are for 640x480 but the camera is set to 1280x720",
        ),
    ],
)
def test_realsense_settings_name_the_field(kwargs: dict[str, Any], message: str | None) -> None:
    if message is None:
        RealSenseCameraSettings(**kwargs)
        return
    with pytest.raises(ValueError, match=re.escape(message)):
        RealSenseCameraSettings(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cti": "producer.so"}, "cti must name a GenTL producer file (*.cti)"),
        ({"cti": "p.cti", "pixel_format": "RGB8"}, "pixel_format must be one of ['Mono8'"),
        ({"cti": "p.cti", "exposure_us": -1}, "exposure_us must be > 0"),
        ({"cti": "p.cti", "gain_db": float("nan")}, "gain_db must be a finite number"),
        ({"cti": "p.cti", "trigger": "line"}, "trigger must be one of ['free_run'"),
        ({"cti": "p.cti", "trigger_source": "Line1"}, "trigger_source is only used with"),
        ({"cti": "p.cti", "trigger": "hardware", "trigger_source": ""}, "trigger_source must"),
        ({"cti": "p.cti", "serial": 42}, "serial must be a non-empty string"),
    ],
)
def test_genicam_settings_name_the_field(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        GenICamCameraSettings(**kwargs)


def test_a_hardware_trigger_defaults_to_line0() -> None:
    settings = GenICamCameraSettings(Path("p.cti"), trigger="hardware")
    assert settings.trigger_source == "Line0"
    assert GenICamCameraSettings(Path("p.cti")).trigger_source is None
