"""The ``realsense`` and ``genicam`` cameras through a real server on loopback: INSPECT and
CAPTURE from the YAML configuration, with the vendor SDKs replaced by fakes that behave like
the devices (tests/helpers/fake_realsense.py, fake_harvesters.py) in ``sys.modules``."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from fake_harvesters import FakeGigECamera, fake_harvesters
from fake_realsense import FakeDevice, fake_pyrealsense2
from loopback import client_for, run

from protocol import CameraUnavailable
from protocol.images import array_from_payload
from vision_server.cameras import CameraSettings, ManualClock, make_camera
from vision_server.config import ConfigError, ServiceSettings, load_config
from vision_server.frontends.http_live import LiveView
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import CellRuntime, InspectionService, InspectRequest

CONFIG = """\
server: {port: 0}
cameras:
  rgbd: {source: realsense, serial: "123456789012", depth_width: 320, depth_height: 240,
         reconnect_interval_s: 3}
  mono: {source: genicam, cti: producers/fake.cti, serial: "22001234", pixel_format: Mono12,
         trigger: software, exposure_us: 2000, gain_db: 3,
         intrinsics: {width: 64, height: 48, fx: 80, fy: 80, cx: 32, cy: 24}}
inspections:
  - {name: rgbd_present, type: presence, camera: rgbd, measure: mean_intensity, min: 1}
  - {name: mono_present, type: presence, camera: mono, measure: mean_intensity, min: 1}
"""


def write_cell(root: Path) -> Path:
    (root / "producers").mkdir()
    (root / "producers" / "fake.cti").write_bytes(b"fake GenTL producer")
    path = root / "cell.yaml"
    path.write_text(CONFIG, encoding="utf-8")
    return path


def test_inspect_and_capture_on_a_realsense_and_a_genicam_camera(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rs_module, bus = fake_pyrealsense2(FakeDevice("123456789012"))
    monkeypatch.setitem(sys.modules, "pyrealsense2", rs_module)
    gc_modules, network = fake_harvesters(FakeGigECamera("22001234"))
    for name, module in gc_modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    clock = ManualClock()

    def factory(name: str, settings: CameraSettings, base_dir: Path) -> object:
        return make_camera(name, settings, base_dir=base_dir, clock=clock)

    runtime = CellRuntime(write_cell(tmp_path), camera_factory=factory)  # type: ignore[arg-type]

    async def body() -> None:
        server = VisionServer(runtime.catalog, ServerSettings(port=0))
        async with server, client_for(server) as client:
            result = await client.inspect("rgbd_present")
            assert result.passed
            frames = await client.capture("rgbd", depth=True)
            color = array_from_payload(frames.images[0])
            depth = array_from_payload(frames.images[1])
            assert color.shape == (480, 640, 3)
            assert depth.shape == (480, 640)  # aligned to colour from a 320x240 depth stream
            assert depth.dtype == np.uint16
            assert np.all(depth == 800)  # the fake sees a flat scene at 0.8 m
            # The device's own intrinsics, since the configuration gives none.
            assert frames.intrinsics is not None
            assert (frames.intrinsics["fx"], frames.intrinsics["cx"]) == (615.0, 321.5)

            bus.device("123456789012").plugged = False
            with pytest.raises(CameraUnavailable) as excinfo:
                await client.capture("rgbd")
            assert "RealSense device 123456789012 was disconnected" in excinfo.value.message
            bus.device("123456789012").plugged = True
            clock.advance(3.0)
            again = await client.capture("rgbd")
            assert array_from_payload(again.images[0]).shape == (480, 640, 3)

            result = await client.inspect("mono_present")
            assert result.passed
            frames = await client.capture("mono", count=2)
            first, second = (array_from_payload(image) for image in frames.images)
            assert first.shape == (48, 64)
            assert (int(first[0, 0]), int(second[0, 0])) == (2, 3)  # one trigger per frame
            assert frames.intrinsics is not None
            assert frames.intrinsics["fx"] == 80.0
            features = network.camera("22001234").features
            assert (features["PixelFormat"], features["ExposureTime"]) == ("Mono12", 2000.0)

    try:
        run(body())
    finally:
        runtime.close()
    assert bus.pipelines == []  # closing the runtime stopped the RealSense pipeline
    assert not network.camera("22001234").opened  # ... and released the GenICam device


@pytest.mark.parametrize(
    ("camera", "message"),
    [
        (
            "{source: realsense, serial: 1234}",
            "cameras -> c: serial must be a non-empty string (quote a numeric serial in YAML)",
        ),
        ("{source: realsense, fps: 0}", "cameras -> c: fps must be a positive integer"),
        ("{source: realsense, colour: true}", "cameras -> c -> colour: unknown key"),
        ("{source: genicam}", "cameras -> c: missing required key 'cti'"),
        ("{source: genicam, cti: x.so}", "cti must name a GenTL producer file (*.cti)"),
        (
            "{source: genicam, cti: x.cti, pixel_format: RGB8}",
            "cameras -> c: pixel_format must be one of",
        ),
        (
            "{source: genicam, cti: x.cti, trigger: software, trigger_source: Line1}",
            "cameras -> c: trigger_source is only used with trigger: hardware",
        ),
    ],
)
def test_configuration_errors_name_the_camera_and_key(
    tmp_path: Path, camera: str, message: str
) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(f"cameras:\n  c: {camera}\n", encoding="utf-8")
    with pytest.raises(ConfigError) as excinfo:
        load_config(path)
    assert message in str(excinfo.value)
    assert "cell.yaml:2" in str(excinfo.value)


def test_the_live_view_of_a_triggered_camera_fires_no_trigger_and_shows_the_inspected_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A console viewer of a camera with a software (or hardware) trigger must not fire one
    (or take the frame a PLC's trigger started for a robot): it shows the frame the last
    inspection took, and nothing before the first."""
    gc_modules, network = fake_harvesters(FakeGigECamera("22001234"))
    for name, module in gc_modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    config = tmp_path / "cell.yaml"
    (tmp_path / "producers").mkdir()
    (tmp_path / "producers" / "fake.cti").write_bytes(b"fake GenTL producer")
    config.write_text(
        "server: {port: 0}\n"
        "cameras:\n"
        "  mono: {source: genicam, cti: producers/fake.cti, serial: '22001234',\n"
        "         pixel_format: Mono8, trigger: software}\n"
        "inspections:\n"
        "  - {name: mono_present, type: presence, camera: mono, measure: mean_intensity,"
        " min: 1}\n",
        encoding="utf-8",
    )
    runtime = CellRuntime(config)
    service = InspectionService(runtime.catalog, ServiceSettings(workers=1))
    live = LiveView(service, max_fps=1000.0)
    device = network.camera("22001234")

    async def body() -> None:
        assert await live.frame("mono") is None  # no inspection yet: nothing to show
        assert device.frame_number == 0  # ... and no trigger fired for the view
        await service.inspect(InspectRequest("mono_present"))
        taken = device.frame_number
        shown = await live.frame("mono")
        assert shown is not None
        pixels = cv2.imdecode(np.frombuffer(shown.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert abs(int(np.median(pixels)) - taken % 256) <= 1  # the inspected frame
        again = await live.frame("mono")
        assert again is not None
        assert device.frame_number == taken  # viewing fired nothing

    try:
        run(body())
    finally:
        live.close()
        service.close()
        runtime.close()
