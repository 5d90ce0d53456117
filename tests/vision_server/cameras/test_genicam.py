"""The ``genicam`` camera against fake harvesters/genicam modules that behave like GenICam
cameras behind a GenTL producer (tests/helpers/fake_harvesters.py), put in ``sys.modules``."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fake_harvesters import SCENE_BGR, FakeGigECamera, Network, fake_harvesters

from protocol import CameraUnavailable
from vision_server.cameras import GenICamCamera, GenICamCameraSettings, ManualClock
from vision_server.cameras.pixels import convert_pixels

SERIAL = "22001234"


@pytest.fixture
def network(monkeypatch: pytest.MonkeyPatch) -> Network:
    modules, network = fake_harvesters(
        FakeGigECamera(SERIAL, pixel_formats=("Mono8", "Mono10", "Mono12", "Mono16", "BayerRG8"))
    )
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    return network


@pytest.fixture
def cti(tmp_path: Path) -> Path:
    path = tmp_path / "producer.cti"
    path.write_bytes(b"\x7fELF fake GenTL producer")
    return path


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


def camera(cti: Path, clock: ManualClock, **settings: object) -> Iterator[GenICamCamera]:
    cam = GenICamCamera(
        "line_scan",
        GenICamCameraSettings(Path(cti.name), **settings),  # type: ignore[arg-type]
        base_dir=cti.parent,
        clock=clock,
    )
    cam.open()
    try:
        yield cam
    finally:
        cam.close()


def grab_error(cam: GenICamCamera) -> str:
    with pytest.raises(CameraUnavailable) as excinfo:
        cam.grab(timeout_s=0.5)
    return excinfo.value.message


@pytest.mark.parametrize("pixel_format", ["Mono8", "Mono10", "Mono12", "Mono16"])
def test_mono_formats_arrive_as_8_bit_gray(
    network: Network, cti: Path, clock: ManualClock, pixel_format: str
) -> None:
    for cam in camera(cti, clock, pixel_format=pixel_format):
        frame = cam.grab(timeout_s=1.0)
        assert frame.color.shape == (48, 64)
        assert frame.color.dtype == np.uint8
        assert np.all(frame.color == 1)  # the fake's frame 1, back from its top 8 bits
        assert network.camera(SERIAL).features["PixelFormat"] == pixel_format


def test_bayer_is_demosaiced_to_the_scenes_colour(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    for cam in camera(cti, clock, pixel_format="BayerRG8"):
        frame = cam.grab(timeout_s=1.0)
        assert frame.color.shape == (48, 64, 3)
        assert tuple(int(c) for c in frame.color[24, 32]) == SCENE_BGR


@pytest.mark.parametrize(
    ("pixel_format", "red_at"), [("BayerGR8", (0, 1)), ("BayerGB8", (1, 0)), ("BayerBG8", (1, 1))]
)
def test_every_bayer_order_keeps_red_red(pixel_format: str, red_at: tuple[int, int]) -> None:
    mosaic = np.full((8, 8), 100, np.uint8)
    mosaic[red_at[0] :: 2, red_at[1] :: 2] = 200
    mosaic[1 - red_at[0] :: 2, 1 - red_at[1] :: 2] = 10
    bgr = convert_pixels(mosaic.reshape(-1), pixel_format=pixel_format, width=8, height=8)
    assert tuple(int(c) for c in bgr[4, 4]) == (10, 100, 200)


def test_high_bit_depths_scale_round_and_saturate() -> None:
    values = np.array([0, 7, 9, 4095, 4096, 65535], np.uint16)
    got = convert_pixels(values, pixel_format="Mono12", width=6, height=1)
    assert got.tolist() == [[0, 0, 1, 255, 255, 255]]
    got = convert_pixels(np.array([0, 127, 129, 65535], np.uint16), pixel_format="Mono16",
                         width=4, height=1)  # fmt: skip
    assert got.tolist() == [[0, 0, 1, 255]]


def test_a_buffer_of_the_wrong_size_is_named() -> None:
    with pytest.raises(ValueError, match="a Mono12 frame of 4x4 has 16 pixels, the buffer holds 8"):
        convert_pixels(np.zeros(8, np.uint16), pixel_format="Mono12", width=4, height=4)


def test_exposure_and_gain_are_set_and_auto_turned_off(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    for cam in camera(cti, clock, exposure_us=1500.0, gain_db=6.0):
        cam.grab(timeout_s=1.0)
        features = network.camera(SERIAL).features
        assert features["ExposureTime"] == 1500.0
        assert features["Gain"] == 6.0
        assert features["ExposureAuto"] == "Off"
        assert features["GainAuto"] == "Off"
        assert features["TriggerMode"] == "Off"


def test_settings_outside_the_devices_range_are_refused_naming_the_key(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    for cam in camera(cti, clock, exposure_us=5.0):
        message = grab_error(cam)
        assert "camera 'line_scan' (genicam)" in message
        assert "exposure_us 5 is outside the device's ExposureTime range [20, 1e+06]" in message
    assert not network.camera(SERIAL).opened  # released for the next attempt
    for cam in camera(cti, clock, gain_db=30.0):
        assert "gain_db 30 is outside the device's Gain range [0, 24]" in grab_error(cam)
    network.camera(SERIAL).pixel_formats = ("Mono8",)
    for cam in camera(cti, clock, pixel_format="Mono12"):
        assert "pixel_format: the device's PixelFormat offers ['Mono8'], not 'Mono12'" in (
            grab_error(cam)
        )


def test_free_run_drops_buffers_filled_before_the_grab(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    for cam in camera(cti, clock):
        assert cam.grab(timeout_s=1.0).color[0, 0] == 1
        network.queue_stale(SERIAL, 3)  # frames 2..4
        assert cam.grab(timeout_s=1.0).color[0, 0] == 5
        # Every buffer went back to the producer's pool (it has four).
        assert network.camera(SERIAL).held == 0


def test_software_trigger_fires_one_frame_per_grab(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    for cam in camera(cti, clock, trigger="software"):
        assert cam.grab(timeout_s=1.0).color[0, 0] == 1
        features = network.camera(SERIAL).features
        assert (features["TriggerMode"], features["TriggerSource"]) == ("On", "Software")
        assert cam.grab(timeout_s=1.0).color[0, 0] == 2
        assert network.camera(SERIAL).frame_number == 2  # one exposure per grab


def test_hardware_trigger_waits_for_the_line(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    for cam in camera(cti, clock, trigger="hardware", trigger_source="Line1"):
        assert "no trigger on Line1 from 22001234 within 0.5 s" in grab_error(cam)
        assert cam.status()["connected"]  # a missing trigger is no lost device
        network.pulse(SERIAL, "Line0")  # the wrong line: nothing
        network.pulse(SERIAL, "Line1")
        network.pulse(SERIAL, "Line1")
        # Triggered frames come out in trigger order, none dropped.
        assert cam.grab(timeout_s=1.0).color[0, 0] == 1
        assert cam.grab(timeout_s=1.0).color[0, 0] == 2


def test_a_hardware_trigger_before_the_first_request_is_not_lost(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    """open() arms the camera: a PLC may trigger before the robot's first request."""
    for cam in camera(cti, clock, trigger="hardware"):
        assert network.camera(SERIAL).acquiring
        network.pulse(SERIAL, "Line0")
        assert cam.grab(timeout_s=1.0).color[0, 0] == 1


def test_new_settings_take_the_device_once_the_old_camera_releases_it(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    """A reload opens the new camera while the old one still holds the device (GenTL opens a
    device for one client): the new one's first request after the old closes connects."""
    for old in camera(cti, clock, exposure_us=1000.0):
        old.grab(timeout_s=1.0)
        for new in camera(cti, clock, exposure_us=3000.0):
            assert new.status()["state"] == "down"
            assert "is opened by another client" in str(new.status()["last_error"])
            old.close()
            new.grab(timeout_s=1.0)  # no reconnect pause: open() failed, not the device
            assert network.camera(SERIAL).features["ExposureTime"] == 3000.0


def test_unplugged_mid_stream_then_back_reconnects(
    network: Network, cti: Path, clock: ManualClock
) -> None:
    for cam in camera(cti, clock, reconnect_interval_s=5.0):
        cam.grab(timeout_s=1.0)
        network.unplug(SERIAL)
        assert "GenICam device 22001234 stopped answering" in grab_error(cam)
        assert not network.camera(SERIAL).opened  # destroyed: the device can be opened again
        assert cam.status()["state"] == "down"
        network.plug(SERIAL)
        assert "stopped answering; retrying every 5 s" in grab_error(cam)
        clock.advance(5.0)
        assert cam.grab(timeout_s=1.0).index == 1
        assert cam.status()["reconnects"] == 1


def test_device_selection_and_producer_errors(
    monkeypatch: pytest.MonkeyPatch, cti: Path, clock: ManualClock
) -> None:
    modules, network = fake_harvesters(FakeGigECamera("A1"), FakeGigECamera("B2"))
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    for cam in camera(cti, clock, serial="B2"):
        cam.grab(timeout_s=1.0)
        assert cam.status()["serial"] == "B2"
    for cam in camera(cti, clock):
        assert (
            "several are visible through producer.cti (serials: A1, B2); set serial to choose one"
        ) in grab_error(cam)
    for cam in camera(cti, clock, serial="C3"):
        assert "no GenICam device with serial C3 through producer.cti (visible: A1, B2)" in (
            grab_error(cam)
        )
    network.camera("A1").opened = True  # another process holds it
    for cam in camera(cti, clock, serial="A1"):
        assert "opening GenICam device A1 failed: device A1 is opened by another" in (
            grab_error(cam)
        )
    cti.unlink()
    for cam in camera(cti, clock, serial="B2"):
        message = grab_error(cam)
        # The producer is named as configured, not by the server's absolute path.
        assert "the GenTL producer producer.cti does not exist" in message
        assert str(cti.parent) not in message


def test_without_harvesters_the_camera_says_which_extra_to_install(
    monkeypatch: pytest.MonkeyPatch, cti: Path, clock: ManualClock
) -> None:
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    for cam in camera(cti, clock):
        assert "pip install 'cellvision[genicam]'" in grab_error(cam)
