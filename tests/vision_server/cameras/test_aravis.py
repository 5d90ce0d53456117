"""The ``aravis`` source against a real GigE Vision device: Aravis' own emulator
(``arv-fake-gv-camera-0.8``) on loopback, speaking GVCP and GVSP, with its GenICam XML.

Each test starts its own emulator on an address of its own (tests/helpers/aravis_emulator.py)
and skips, naming what is missing, only where Aravis or the emulator cannot be installed.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aravis_emulator
import numpy as np
import pytest
from console_server import Browserless, running_cell

from protocol import CameraUnavailable
from robot_client.client import VisionClient
from vision_server.cameras import AravisCamera, AravisCameraSettings


@pytest.fixture
def device() -> Iterator[aravis_emulator.Emulator]:
    try:
        with aravis_emulator.emulator("CV0001") as running:
            yield running
    except aravis_emulator.Unavailable as exc:
        pytest.skip(str(exc))


def settings(device: aravis_emulator.Emulator, **kw: Any) -> AravisCameraSettings:
    kw.setdefault("address", device.address)
    kw.setdefault("reconnect_interval_s", 0.2)
    return AravisCameraSettings(**kw)


def grab_error(camera: AravisCamera, timeout_s: float = 1.0) -> str:
    with pytest.raises(CameraUnavailable) as caught:
        camera.grab(timeout_s=timeout_s)
    return str(caught.value)


def last_frame(camera: AravisCamera) -> dict[str, Any]:
    last = camera.status()["last_frame"]
    assert last is not None
    return dict(last)


RAMP = {"exposure_us": 10000.0, "gain_db": 0.0}
"""The settings at which the emulator's frame is its plain ramp (aravis_emulator)."""


def test_the_frames_are_the_emulators_frames(device: aravis_emulator.Emulator) -> None:
    region = (8, 4, 64, 48)
    with AravisCamera("gv", settings(device, trigger="software", region=region, **RAMP)) as cam:
        cam.open()
        ids = []
        for _ in range(3):
            frame = cam.grab(timeout_s=5.0)
            last = last_frame(cam)
            assert frame.color.shape == (48, 64)
            assert last["region"] == list(region)
            np.testing.assert_array_equal(
                frame.color, aravis_emulator.expected_ramp(last["frame_id"], region)
            )
            ids.append(last["frame_id"])
        # Each grab fires one software trigger and takes its frame: new block IDs in order
        # (consecutive unless a trigger had to be fired again on a loaded machine).
        assert ids == sorted(set(ids))
        status = cam.status()
        assert status["serial"] == "CV0001"
        assert status["address"] == device.address
        assert status["protocol"] == "GigE Vision"
        assert status["stream"]["frames_completed"] >= 3
        assert status["stream"]["packets_received"] > 0


def test_found_by_serial_among_the_discovered_devices(device: aravis_emulator.Emulator) -> None:
    found = AravisCameraSettings(serial="CV0001", trigger="software", **RAMP)
    with AravisCamera("gv", found) as cam:
        frame = cam.grab(timeout_s=5.0)
        assert cam.status()["address"] == device.address
        # No region configured: the whole sensor (not the emulator's 512x512 at start).
        sensor = (0, 0, *aravis_emulator.SENSOR)
        assert last_frame(cam)["region"] == list(sensor)
        np.testing.assert_array_equal(
            frame.color, aravis_emulator.expected_ramp(last_frame(cam)["frame_id"], sensor)
        )
    with AravisCamera("gv", AravisCameraSettings(serial="NO-SUCH-SERIAL")) as cam:
        message = grab_error(cam)
    assert "the device with serial NO-SUCH-SERIAL is not visible" in message
    assert "CV0001" in message  # what is visible


def test_free_run_takes_a_frame_made_after_the_grab(device: aravis_emulator.Emulator) -> None:
    s = settings(device, frame_rate_hz=50.0, region=(0, 0, 256, 256), **RAMP)
    with AravisCamera("gv", s) as cam:
        cam.grab(timeout_s=5.0)
        first = last_frame(cam)["frame_id"]
        time.sleep(0.2)  # frames pile up in the stream's buffers meanwhile
        cam.grab(timeout_s=5.0)
        # The stale frames were dropped: the grab's frame is newer than those delivered
        # while nobody asked (at 50 Hz, about 10 of them).
        assert last_frame(cam)["frame_id"] >= first + 5
        assert cam.status()["stream"]["frames_completed"] >= 5


def test_exposure_and_gain_change_the_emulators_image(device: aravis_emulator.Emulator) -> None:
    region = (0, 0, 128, 128)  # every grey level of the ramp

    def mean_ratio(**kw: Any) -> float:
        with AravisCamera("gv", settings(device, trigger="software", region=region, **kw)) as cam:
            frame = cam.grab(timeout_s=5.0)
            ramp = aravis_emulator.expected_ramp(last_frame(cam)["frame_id"], region)
        lit = (ramp > 20) & (ramp < 100)  # away from saturation
        return float(np.mean(frame.color[lit] / ramp[lit]))

    assert mean_ratio(**RAMP) == pytest.approx(1.0)
    assert mean_ratio(exposure_us=20000.0, gain_db=0.0) > 1.1
    assert mean_ratio(exposure_us=10000.0, gain_db=1.0) > 1.5


@pytest.mark.parametrize(
    ("pixel_format", "shape"),
    [("Mono8", (32, 32)), ("Mono16", (32, 32)), ("RGB8", (32, 32, 3)), ("BayerRG8", (32, 32, 3))],
)
def test_pixel_formats(
    device: aravis_emulator.Emulator, pixel_format: str, shape: tuple[int, ...]
) -> None:
    s = settings(device, trigger="software", pixel_format=pixel_format, region=(0, 0, 32, 32))
    with AravisCamera("gv", s) as cam:
        frame = cam.grab(timeout_s=5.0)
    assert frame.color.shape == shape
    assert frame.color.dtype == np.uint8
    assert frame.color.std() > 0  # the ramp, not a blank frame


@pytest.mark.parametrize(
    ("kw", "expected"),
    [
        (
            {"exposure_us": 5e7},
            "exposure_us 5e+07 is outside the device's ExposureTime range [10, 1e+07] us",
        ),
        ({"gain_db": 20.0}, "gain_db 20 is outside the device's Gain range [0, 10] dB"),
        (
            {"pixel_format": "Mono12"},
            "pixel_format: the device's PixelFormat offers ['BayerBG8', 'BayerGB8', 'BayerGR8', "
            "'BayerRG8', 'Mono8', 'RGB8', 'Mono16'], not 'Mono12'",
        ),
        (
            {"region": (2000, 0, 64, 64)},
            "region [2000, 0, 64, 64] does not fit the device's sensor of 2048x2048",
        ),
        (
            {"trigger": "hardware", "trigger_source": "Line3"},
            "trigger_source: the device's TriggerSource offers ['Line0', 'Software'], not 'Line3'",
        ),
        (
            {"frame_rate_hz": 5000.0},
            "frame_rate_hz 5000 is outside the device's AcquisitionFrameRate range [0.1, 1000]",
        ),
    ],
    ids=["exposure", "gain", "pixel_format", "region", "trigger_source", "frame_rate"],
)
def test_a_setting_outside_the_devices_range_is_refused_by_name(
    device: aravis_emulator.Emulator, kw: dict[str, Any], expected: str
) -> None:
    with AravisCamera("gv", settings(device, **kw)) as cam:
        message = grab_error(cam)
        assert expected in message
        assert cam.status()["state"] == "down"


def test_a_packet_size_outside_the_devices_range_is_refused(
    device: aravis_emulator.Emulator,
) -> None:
    with AravisCamera("gv", settings(device, packet_size=65000)) as cam:
        message = grab_error(cam)
    assert "packet_size 65000 is outside the device's GevSCPSPacketSize range" in message


def test_a_larger_packet_size_sends_fewer_packets(device: aravis_emulator.Emulator) -> None:
    counts = {}
    for size in (1400, 8000):
        s = settings(device, trigger="software", packet_size=size, region=(0, 0, 256, 256))
        with AravisCamera("gv", s) as cam:
            cam.grab(timeout_s=5.0)
            counts[size] = cam.status()["stream"]["packets_received"]
    assert counts[8000] < counts[1400] / 3


def test_a_hardware_trigger_that_never_comes_times_out_and_stays_connected(
    device: aravis_emulator.Emulator,
) -> None:
    with AravisCamera("gv", settings(device, trigger="hardware")) as cam:
        message = grab_error(cam, timeout_s=0.5)
        assert "no trigger on Line0 from Fake CV0001" in message
        assert "within 0.5 s" in message
        assert cam.status()["state"] == "up"


def test_the_emulator_killed_and_restarted_mid_stream(device: aravis_emulator.Emulator) -> None:
    region = (0, 0, 64, 64)
    with AravisCamera("gv", settings(device, trigger="software", region=region, **RAMP)) as cam:
        cam.grab(timeout_s=5.0)
        device.kill()
        message = grab_error(cam, timeout_s=1.0)
        assert "stopped answering" in message or "failed" in message
        assert cam.status()["state"] == "down"
        # Down, it answers at once with the cause until the next attempt is due.
        assert "retrying every 0.2 s" in grab_error(cam)
        device.start()
        deadline = time.monotonic() + 30.0
        while True:
            try:
                frame = cam.grab(timeout_s=5.0)
                break
            except CameraUnavailable:
                assert time.monotonic() < deadline, "the device came back, the camera did not"
                time.sleep(0.2)
        status = cam.status()
        assert status["state"] == "up"
        assert status["reconnects"] == 1
        np.testing.assert_array_equal(
            frame.color, aravis_emulator.expected_ramp(last_frame(cam)["frame_id"], region)
        )
        # The statistics of the stream before the kill are kept.
        assert status["stream"]["frames_completed"] >= 2


def test_lost_packets_are_counted_and_complete_frames_still_come() -> None:
    try:
        with aravis_emulator.emulator("CVLOSS", lost_per_thousand=5) as lossy:
            region = (0, 0, 512, 512)
            s = settings(lossy, trigger="software", packet_size=1400, region=region, **RAMP)
            with AravisCamera("gv", s) as cam:
                for _ in range(10):
                    frame = cam.grab(timeout_s=10.0)
                    # Only a complete frame is handed on: an incomplete one is triggered again.
                    np.testing.assert_array_equal(
                        frame.color,
                        aravis_emulator.expected_ramp(last_frame(cam)["frame_id"], region),
                    )
                stream = cam.status()["stream"]
    except aravis_emulator.Unavailable as exc:
        pytest.skip(str(exc))
    # A 512x512 frame is ~190 packets of 1400 bytes: at 0.5 % lost, about 60 % of the frames
    # miss one (and the emulator resends none), so ten good frames take ~25 triggers.
    assert stream["frames_completed"] >= 10
    assert stream["frames_failed"] > 0
    assert stream["packets_missing"] > 0


def test_a_refused_setting_gives_the_device_back_at_once(
    device: aravis_emulator.Emulator,
) -> None:
    """A camera whose setting the device refuses releases its GigE Vision control when it
    goes down, so the corrected camera (a reload) takes the device at its first grab."""
    with AravisCamera("bad", settings(device, exposure_us=5e7)) as bad:
        assert "outside the device's ExposureTime range" in grab_error(bad)
        with AravisCamera("good", settings(device, trigger="software")) as good:
            good.grab(timeout_s=5.0)
            assert good.status()["reconnects"] == 0


def test_a_region_left_by_an_earlier_client_is_not_kept(
    device: aravis_emulator.Emulator,
) -> None:
    with AravisCamera("first", settings(device, trigger="software", region=(4, 4, 100, 80))) as a:
        assert a.grab(timeout_s=5.0).color.shape == (80, 100)
    with AravisCamera("second", settings(device, trigger="software")) as b:
        assert b.grab(timeout_s=5.0).color.shape == aravis_emulator.SENSOR[::-1]


def test_two_clients_on_one_device(device: aravis_emulator.Emulator) -> None:
    first = AravisCamera("first", settings(device, trigger="software"))
    second = AravisCamera("second", settings(device, trigger="software"))
    try:
        first.grab(timeout_s=5.0)
        message = grab_error(second, timeout_s=1.0)
        assert "Fake CV0001 at" in message
        assert "is controlled by another application" in message
        first.grab(timeout_s=5.0)  # the controller is not disturbed
        first.close()
        deadline = time.monotonic() + 30.0
        while True:
            try:
                second.grab(timeout_s=5.0)
                break
            except CameraUnavailable:
                assert time.monotonic() < deadline, "the second never took over"
                time.sleep(0.2)
        assert second.status()["reconnects"] == 1
    finally:
        first.close()
        second.close()


CELL = """\
server:
  host: 127.0.0.1
  port: 0
  name: aravis-cell
console:
  enabled: true
  port: 0
  max_view_fps: 30
cameras:
  gv: {{source: aravis, address: "{address}", frame_rate_hz: 30, exposure_us: 10000,
       gain_db: 0, region: [0, 0, 128, 96]}}
inspections:
  - name: lit
    type: presence
    camera: gv
    roi: [0, 0, 128, 96]
    measure: mean_intensity
    min: 1
"""


def test_through_the_server(device: aravis_emulator.Emulator, tmp_path: Path) -> None:
    config = tmp_path / "cell.yaml"
    config.write_text(CELL.format(address=device.address), encoding="utf-8")
    with running_cell(config) as running:

        async def inspect() -> Any:
            async with VisionClient("127.0.0.1", running.app.port, request_timeout_s=20.0) as c:
                return await c.inspect("lit")

        result = asyncio.run(inspect())
        assert result.passed, result
        web = Browserless(running.url)
        cameras = {c["name"]: c for c in web.get("/api/cameras").json()["cameras"]}
        gv = cameras["gv"]
        assert gv["source"] == "aravis"
        assert gv["stream"]["frames_completed"] >= 1
        assert gv["device"]["serial"] == "CV0001"
        metrics = web.get("/metrics").body.decode()
        assert 'cellvision_camera_stream_frames_total{camera="gv",outcome="completed"}' in metrics
        assert 'cellvision_camera_connected{camera="gv"} 1.0' in metrics
        # The live view takes the free-running camera's frames.
        deadline = time.monotonic() + 20.0
        while True:
            frame = web.get("/api/cameras/gv/frame.jpg")
            if frame.status == 200:
                break
            assert time.monotonic() < deadline, (frame.status, frame.body[:200])
            time.sleep(0.2)
        assert frame.body[:3] == b"\xff\xd8\xff"

        # A second server configured with the same device: its requests are refused with the
        # cause, the first server's go on.
        other = tmp_path / "other"
        other.mkdir()
        (other / "cell.yaml").write_text(CELL.format(address=device.address), encoding="utf-8")
        with running_cell(other / "cell.yaml") as second:

            async def inspect_second() -> str:
                async with VisionClient("127.0.0.1", second.app.port, request_timeout_s=30.0) as c:
                    with pytest.raises(CameraUnavailable) as caught:
                        await c.inspect("lit")
                    return str(caught.value)

            message = asyncio.run(inspect_second())
            assert "is controlled by another application" in message
            assert asyncio.run(inspect()).passed


def test_two_cameras_of_one_configuration_on_one_device_are_refused(tmp_path: Path) -> None:
    from vision_server.config import ConfigError, load_config

    config = tmp_path / "cell.yaml"
    config.write_text(
        "cameras:\n"
        "  a: {source: aravis, serial: '22001234'}\n"
        "  b: {source: aravis, serial: '22001234', trigger: software}\n",
        encoding="utf-8",
    )
    with pytest.raises(ConfigError, match="camera 'a' already uses the device with serial"):
        load_config(config)
