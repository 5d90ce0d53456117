"""The ``realsense`` camera against the real pyrealsense2: recordings written with
:class:`RealSenseRecorder` (the SDK's ``software_device`` + ``recorder``) and played back by
``RealSenseCamera`` with ``playback:`` through the SDK's own pipeline and ``align``.

No fake here: what the SDK does with a recording (its timestamps, depth units, alignment,
the end of the file, the framesets it hands over) is what these tests see. The frames are the
simulated cell's RGB-D camera looking at the QR code station.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from loopback import run
from numpy.typing import NDArray

from geometry import invert_transform, transform_from_xyz_rpy
from protocol import CameraUnavailable
from simulation import SimCell
from vision_server.cameras import (
    CameraFrame,
    Intrinsics,
    RealSenseCamera,
    RealSenseCameraSettings,
    RealSenseRecorder,
    SimCamera,
    SimCameraSettings,
    make_camera,
)
from vision_server.config import ServiceSettings, load_config
from vision_server.service import CellRuntime, InspectionService, InspectReply, InspectRequest

rs = pytest.importorskip(
    "pyrealsense2", reason="pyrealsense2 (the realsense extra, installed by make bootstrap)"
)

ROOT = Path(__file__).resolve().parents[3]
SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"
# The robot's tool where the RGB-D camera on it sees the QR code station (as in
# tests/robot_client/test_qr_calibration.py).
VIEW = transform_from_xyz_rpy([0.25, -0.36, 0.35], [-np.pi / 2, 0.0, -np.pi / 2])
T0 = 1_765_000_000.0  # the recording's first frame, seconds since the epoch


def f32(value: float) -> float:
    """What the SDK keeps of a number it stores as float (intrinsics, the depth scale)."""
    return float(np.float32(value))


def sim_state(tmp_path: Path) -> Path:
    """A world-state file with the robot's tool at VIEW."""
    state = tmp_path / "world-state.json"
    cell = SimCell.from_yaml(SCENE, state_path=state)
    cell.world.base_from_tool = VIEW
    cell.publish()
    return state


def sim_camera(state: Path, seed: int = 7) -> SimCamera:
    """The scene's RGB-D camera; two with the same seed render the same frames in turn."""
    return SimCamera("sim", SimCameraSettings(SCENE, "rgbd", state_file=state, seed=seed))


def record_sim(
    path: Path, state: Path, n: int, *, depth_scale_m: float, seed: int = 7
) -> list[CameraFrame]:
    """Record ``n`` frames of the simulated RGB-D camera; returns them."""
    cam = sim_camera(state, seed)
    assert cam.intrinsics is not None
    frames = [cam.grab(timeout_s=5.0) for _ in range(n)]
    with RealSenseRecorder(
        path, width=640, height=480, fps=30, intrinsics=cam.intrinsics, depth_scale_m=depth_scale_m
    ) as recorder:
        for i, frame in enumerate(frames):
            recorder.add(frame.color, frame.depth, T0 + i / 30)
    return frames


def playing(path: Path, **settings: Any) -> Iterator[RealSenseCamera]:
    options: dict[str, Any] = {"playback": path.name, **settings}
    cam = RealSenseCamera("rgbd", RealSenseCameraSettings(**options), base_dir=path.parent)
    cam.open()
    try:
        yield cam
    finally:
        cam.close()


def grab_error(cam: RealSenseCamera, timeout_s: float = 10.0) -> str:
    with pytest.raises(CameraUnavailable) as excinfo:
        cam.grab(timeout_s=timeout_s)
    return excinfo.value.message


def grab_to_the_end(cam: RealSenseCamera, most: int) -> tuple[list[CameraFrame], str]:
    """The frames a playback gives (at most ``most``) and the error that ends it."""
    frames: list[CameraFrame] = []
    while len(frames) <= most:
        try:
            frames.append(cam.grab(timeout_s=10.0))
        except CameraUnavailable as exc:
            return frames, exc.message
    raise AssertionError(f"more than {most} frames from a recording of {most}")


@pytest.mark.parametrize(
    ("depth_scale_m", "like"), [(0.0001, "D405"), (0.001, "D435")], ids=["D405", "D435"]
)
def test_recorded_sim_frames_play_back_through_the_sdk(
    tmp_path: Path, depth_scale_m: float, like: str
) -> None:
    path = tmp_path / "station.db3"
    recorded = record_sim(path, sim_state(tmp_path), 6, depth_scale_m=depth_scale_m)
    sim_k = sim_camera(sim_state(tmp_path)).intrinsics
    assert sim_k is not None
    for cam in playing(path):
        # The recording's colour intrinsics, as the SDK stores them (float).
        k = cam.intrinsics
        assert k is not None
        assert (k.width, k.height) == (640, 480)
        assert (k.fx, k.fy, k.cx, k.cy) == tuple(
            f32(v) for v in (sim_k.fx, sim_k.fy, sim_k.cx, sim_k.cy)
        )
        assert k.distortion == sim_k.distortion
        status = cam.status()
        assert status["depth_scale_m"] == f32(depth_scale_m)  # read from the depth sensor
        assert status["model"] == "cellvision RealSenseRecorder"
        frames, message = grab_to_the_end(cam, len(recorded))
        # Each frame is the recorded frame of its timestamp: the SDK's (milliseconds, domain
        # system_time), in seconds. The SDK may lose a frame of a recording (see the module
        # realsense.py); the camera then counts it, and never hands over another frame.
        which = [round((f.timestamp - T0) * 30) for f in frames]
        assert [f.timestamp for f in frames] == pytest.approx(
            [T0 + i / 30 for i in which], abs=1e-6
        )
        assert which == sorted(set(which))  # in order, each once
        assert len(frames) >= len(recorded) - 1, f"the SDK delivered frames {which}"
        for got, i in zip(frames, which, strict=True):
            want = recorded[i]
            assert np.array_equal(got.color, want.color), f"colour of frame {i}"
            assert got.depth is not None
            assert want.depth is not None
            # Millimetres are whole device units at both scales: nothing to round away.
            assert np.array_equal(got.depth, want.depth), f"depth of frame {i}"
        assert [f.index for f in frames] == list(range(len(frames)))
        # The end of a recording that does not loop is a typed error, every time.
        n = len(frames)
        assert f"camera 'rgbd' (realsense): the recording station.db3 ended after {n} frames" in (
            message
        )
        assert str(tmp_path) not in message  # the path as configured
        assert f"ended after {n} frames" in grab_error(cam)
        assert cam.status()["state"] == "ended"
        assert cam.status()["frames"] == n


def test_depth_in_device_units_is_rounded_to_the_depth_scale(tmp_path: Path) -> None:
    """A D435-like 1 mm unit keeps millimetres; a 0.0001 m unit cannot hold 7 m (no depth)."""
    k = Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5)
    depth = np.array([[0, 1, 2, 999, 6553, 7000, 65535, 300]] * 6, np.uint16)
    color = np.zeros((6, 8, 3), np.uint8)
    for scale, want in (
        (0.001, depth),
        (0.0001, np.where(depth > 6553, 0, depth)),
        # 2 mm units: odd millimetres round to even units (numpy's and the recorder's rint)
        (0.002, np.minimum(2 * np.rint(depth / 2), 65535)),
    ):
        path = tmp_path / f"scale-{scale}.db3"
        with RealSenseRecorder(
            path, width=8, height=6, fps=30, intrinsics=k, depth_scale_m=scale
        ) as r:
            r.add(color, depth, T0)
        for cam in playing(path, width=8, height=6):
            got = cam.grab(timeout_s=10.0).depth
            assert got is not None
            assert np.array_equal(got, want), (scale, got[0])


def test_align_puts_depth_of_another_camera_model_on_the_colour_pixels(tmp_path: Path) -> None:
    """Depth recorded at 320x240 with another focal length and principal point than the
    640x480 colour: a box face at 0.6 m before a wall at 0.8 m must land, after the SDK's
    align, where the colour camera sees the box."""
    color_k = Intrinsics(640, 480, 600.0, 600.0, 319.5, 239.5)
    depth_k = Intrinsics(320, 240, 260.0, 270.0, 150.25, 131.75)
    box_x, box_y = (-0.10, 0.12), (-0.06, 0.09)  # the box face's extent at z = 0.6 m

    def seen(k: Intrinsics) -> NDArray[np.uint16]:
        """The depth (mm) a pinhole camera ``k`` at the colour camera's centre sees."""
        u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
        x, y = 0.6 * (u - k.cx) / k.fx, 0.6 * (v - k.cy) / k.fy
        box = (box_x[0] < x) & (x < box_x[1]) & (box_y[0] < y) & (y < box_y[1])
        return np.where(box, 600, 800).astype(np.uint16)

    path = tmp_path / "align.db3"
    color = np.full((480, 640, 3), 128, np.uint8)
    with RealSenseRecorder(
        path, width=640, height=480, fps=30, intrinsics=color_k, depth_intrinsics=depth_k
    ) as recorder:
        recorder.add(color, seen(depth_k), T0)
    for cam in playing(path):
        depth = cam.grab(timeout_s=10.0).depth
        assert depth is not None
        assert depth.shape == (480, 640)
        want = seen(color_k)
        # Away from the box's edges (a pixel of depth covers two of colour there).
        u, v = np.meshgrid(np.arange(640), np.arange(480))
        x, y = 0.6 * (u - color_k.cx) / color_k.fx, 0.6 * (v - color_k.cy) / color_k.fy
        margin = 3 * 0.6 / color_k.fx
        near_edge = ((np.abs(x - box_x[0]) < margin) | (np.abs(x - box_x[1]) < margin)) | (
            (np.abs(y - box_y[0]) < margin) | (np.abs(y - box_y[1]) < margin)
        )
        inside_depth_view = depth > 0
        check = ~near_edge & inside_depth_view
        assert check.mean() > 0.9
        assert np.array_equal(depth[check], want[check])
        # At the box's edges the nearer surface wins (the SDK keeps the nearest depth where
        # the footprints of two depth pixels overlap): the box grows by at most a pixel.
        ring = 222 * 152 - 220 * 150  # one pixel around the 220x150 pixels of the box face
        grown = int((depth == 600).sum()) - int((want == 600).sum())
        assert 0 <= grown <= ring
        # A plain resize of the depth image would have put the box elsewhere: a third of the
        # box face's 33,000 pixels wrong.
        resized = np.kron(seen(depth_k), np.ones((2, 2), np.uint16))
        assert (resized[check] != want[check]).sum() > 10_000


def test_qr_pose_on_the_playback_agrees_with_the_simulated_camera(tmp_path: Path) -> None:
    """The station_pose inspection (examples/cell.yaml's) through the inspection service, on
    the simulated RGB-D camera and on the playback of a recording of the same frames."""
    state = sim_state(tmp_path)
    path = tmp_path / "station.db3"
    record_sim(path, state, 5, depth_scale_m=0.0001)
    pose = "method: plane, expect: 'cellvision:station-1', side_m: 0.16, max_plane_rms_m: 0.005"
    cell = tmp_path / "cell.yaml"
    cell.write_text(
        f"""\
results: {{enabled: false}}
cameras:
  sim: {{source: sim, scene: '{SCENE}', camera: rgbd, state_file: world-state.json, seed: 7}}
  rec: {{source: realsense, playback: station.db3}}
inspections:
  - {{name: pose_sim, type: qr_pose, camera: sim, {pose}}}
  - {{name: pose_rec, type: qr_pose, camera: rec, {pose}}}
""",
        encoding="utf-8",
    )
    config = load_config(cell)
    assert config.cameras["rec"].playback == Path("station.db3")
    runtime = CellRuntime(cell)
    service = InspectionService(runtime.catalog, ServiceSettings(workers=1))

    async def body() -> dict[str, InspectReply]:
        replies = {}
        for name in ("pose_sim", "pose_rec"):
            replies[name] = await service.inspect(InspectRequest(name))
        return replies

    try:
        replies = run(body())
    finally:
        service.close()
        runtime.close()
    poses = {}
    for name, reply in replies.items():
        assert reply.passed, (name, reply.data)
        poses[name] = np.asarray(reply.data["camera_from_qr"])
    delta = invert_transform(poses["pose_sim"]) @ poses["pose_rec"]
    translation_mm = 1000 * float(np.linalg.norm(delta[:3, 3]))
    angle_deg = float(np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1))))
    # The same frames (colour bit for bit, depth to the unit, registered depth not resampled)
    # and the recording's float intrinsics (570.3 px stored as 570.29999 px): the poses
    # differed by 3e-5 mm and 2e-6 degrees when this was written.
    assert translation_mm < 0.001, translation_mm
    assert angle_deg < 0.0001, angle_deg


def test_colour_alone_and_the_streams_a_recording_lacks(tmp_path: Path) -> None:
    k = Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5)
    color = np.full((6, 8, 3), 77, np.uint8)
    both, alone = tmp_path / "both.db3", tmp_path / "colour.db3"
    with RealSenseRecorder(both, width=8, height=6, fps=30, intrinsics=k) as recorder:
        recorder.add(color, np.full((6, 8), 400, np.uint16), T0)
    with RealSenseRecorder(alone, width=8, height=6, fps=15, intrinsics=k, depth=False) as recorder:
        recorder.add(color, None, T0)
    for path in (both, alone):
        for cam in playing(path, width=8, height=6, depth=False):
            frame = cam.grab(timeout_s=10.0)
            assert frame.depth is None
            assert np.array_equal(frame.color, color)
    for cam in playing(alone, width=8, height=6):
        message = grab_error(cam)
        assert "the recording colour.db3 has no depth stream (it has: color)" in message
        assert "set depth: false" in message


def test_a_recording_that_does_not_fit_is_named(tmp_path: Path) -> None:
    (tmp_path / "text.db3").write_text("not a recording", encoding="utf-8")
    (tmp_path / "notes.bag").write_text("not a recording either", encoding="utf-8")
    for cam in playing(tmp_path / "missing.db3"):
        assert "the recording missing.db3 does not exist" in grab_error(cam)
        assert cam.status()["state"] == "down"
    for name in ("text.db3", "notes.bag"):
        for cam in playing(tmp_path / name):
            message = grab_error(cam)
            assert f"the file {name} is not a RealSense recording the SDK can read" in message
    path = tmp_path / "small.db3"
    k = Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5)
    with RealSenseRecorder(
        path, width=8, height=6, fps=30, intrinsics=k, depth_intrinsics=Intrinsics(4, 3, 5, 5, 2, 1)
    ) as recorder:
        recorder.add(np.zeros((6, 8, 3), np.uint8), np.zeros((3, 4), np.uint16), T0)
    for cam in playing(path, width=640, height=480):  # a size given must be the recording's
        message = grab_error(cam)
        assert (
            "the recording small.db3's colour stream is 8x6 but the camera is set to 640x480"
            in message
        )
    for cam in playing(path, width=8, height=6, depth_width=8, depth_height=6):
        assert "small.db3's depth stream is 4x3 but the camera is set to 8x6" in grab_error(cam)
    # 12 depth pixels would have to go through the SDK's align, which then corrupts memory.
    for cam in playing(path, width=8, height=6, depth_width=4, depth_height=3):
        assert "4x3, whose pixel count is not a multiple of 8" in grab_error(cam)


def one_stream_recording(path: Path, kind: Any, fmt: Any, model: Any, coeffs: list[float]) -> None:
    """A recording of one 8x6 stream of one frame, written with the SDK directly: what
    RealSenseRecorder does not write (a depth stream alone, RGB, another distortion model)."""
    bpp = 2 if fmt == rs.format.z16 else 3
    device = rs.software_device()
    sensor = device.add_sensor("Depth" if kind == rs.stream.depth else "Color")
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = kind, 0, 1
    stream.width, stream.height, stream.fps, stream.bpp, stream.fmt = 8, 6, 30, bpp, fmt
    k = rs.intrinsics()
    k.width, k.height, k.fx, k.fy, k.ppx, k.ppy = 8, 6, 10.0, 10.0, 3.5, 2.5
    k.model, k.coeffs = model, coeffs
    stream.intrinsics = k
    profile = sensor.add_video_stream(stream).as_video_stream_profile()
    recorder = rs.recorder(str(path), device, False)
    recording = recorder.query_sensors()[0]
    recording.open(recording.get_stream_profiles()[0])
    recording.start(lambda frame: None)
    frame = rs.software_video_frame()
    if bpp == 2:
        frame.pixels = np.zeros((6, 8), np.uint16)
    else:  # R = 200, G = 100, B = 50
        frame.pixels = np.tile(np.array([200, 100, 50], np.uint8), (6, 8, 1))
    frame.stride, frame.bpp, frame.timestamp, frame.frame_number = 8 * bpp, bpp, 1000.0, 1
    frame.domain, frame.profile = rs.timestamp_domain.system_time, profile
    sensor.on_video_frame(frame)
    recording.stop()
    recording.close()
    del recording, recorder, sensor, device, profile, frame


def test_a_recording_without_colour_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "depth-only.db3"
    one_stream_recording(path, rs.stream.depth, rs.format.z16, rs.distortion.none, [0.0] * 5)
    for cam in playing(path, width=8, height=6):
        message = grab_error(cam)
        assert "the recording depth-only.db3 has no colour stream (it has: depth)" in message


def test_rgb_colour_distortion_and_configured_intrinsics(tmp_path: Path) -> None:
    """An rgb8 recording comes back as BGR; Brown-Conrady coefficients are OpenCV's; another
    model with coefficients is refused; intrinsics in the configuration win."""
    rgb = tmp_path / "rgb.db3"
    coeffs = [0.1, -0.2, 0.001, 0.002, 0.03]
    one_stream_recording(rgb, rs.stream.color, rs.format.rgb8, rs.distortion.brown_conrady, coeffs)
    for cam in playing(rgb, width=8, height=6, depth=False):
        assert cam.grab(timeout_s=10.0).color[0, 0].tolist() == [50, 100, 200]
        assert cam.intrinsics == Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5, tuple(map(f32, coeffs)))
    mine = Intrinsics(8, 6, 11.0, 11.0, 4.0, 3.0)
    for cam in playing(rgb, width=8, height=6, depth=False, intrinsics=mine):
        assert cam.intrinsics == mine
        assert cam.grab(timeout_s=10.0).color.shape == (6, 8, 3)
        assert cam.intrinsics == mine
    ftheta = tmp_path / "ftheta.db3"
    one_stream_recording(ftheta, rs.stream.color, rs.format.bgr8, rs.distortion.ftheta, coeffs)
    for cam in playing(ftheta, width=8, height=6, depth=False):
        assert "distortion model distortion.ftheta is not OpenCV's" in grab_error(cam)


def test_the_recorder_refuses_what_it_cannot_write(tmp_path: Path) -> None:
    k = Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5)
    with pytest.raises(ValueError, match=r"must be named \*.db3"):
        RealSenseRecorder(tmp_path / "x.bag", width=8, height=6, fps=30, intrinsics=k)
    with pytest.raises(ValueError, match="intrinsics are for 8x6 but the colour stream is 16x12"):
        RealSenseRecorder(tmp_path / "x.db3", width=16, height=12, fps=30, intrinsics=k)
    with pytest.raises(ValueError, match="beyond k3"):
        RealSenseRecorder(
            tmp_path / "x.db3", width=8, height=6, fps=30,
            intrinsics=Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5, (0, 0, 0, 0, 0, 0.1, 0, 0)),
        )  # fmt: skip
    with RealSenseRecorder(tmp_path / "x.db3", width=8, height=6, fps=30, intrinsics=k) as r:
        r.add(np.zeros((6, 8, 3), np.uint8), np.zeros((6, 8), np.uint16), T0)
        with pytest.raises(ValueError, match="time_s must increase"):
            r.add(np.zeros((6, 8, 3), np.uint8), np.zeros((6, 8), np.uint16), T0)
        with pytest.raises(ValueError, match=r"depth_mm must be \(6, 8\) uint16"):
            r.add(np.zeros((6, 8, 3), np.uint8), np.zeros((6, 8), np.float32), T0 + 1)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="give depth_mm"):
            r.add(np.zeros((6, 8, 3), np.uint8), None, T0 + 1)
        with pytest.raises(ValueError, match=r"color_bgr must be \(6, 8, 3\)"):
            r.add(np.zeros((6, 9, 3), np.uint8), np.zeros((6, 8), np.uint16), T0 + 1)
        # A gray image is written as BGR.
        r.add(np.full((6, 8), 9, np.uint8), np.zeros((6, 8), np.uint16), T0 + 1 / 30)
    with pytest.raises(ValueError, match="closed"):
        r.add(np.zeros((6, 8, 3), np.uint8), np.zeros((6, 8), np.uint16), T0 + 2 / 30)
    for cam in playing(tmp_path / "x.db3", width=8, height=6):
        cam.grab(timeout_s=10.0)
        assert np.all(cam.grab(timeout_s=10.0).color == 9)


def test_playback_settings_are_checked(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="serial and playback exclude each other"):
        RealSenseCameraSettings(serial="123", playback=Path("x.db3"))
    with pytest.raises(TypeError, match="loop_file"):
        RealSenseCameraSettings(loop_file=True)  # type: ignore[call-arg]  # no looping
    # make_camera resolves the recording against the configuration's directory.
    cam = make_camera("rgbd", RealSenseCameraSettings(playback=Path("a/x.db3")), base_dir=tmp_path)
    assert isinstance(cam, RealSenseCamera)
    assert cam.playback_path == tmp_path / "a" / "x.db3"


def test_a_playback_without_a_size_plays_the_recordings_own(tmp_path: Path) -> None:
    path = tmp_path / "wide.db3"
    k = Intrinsics(16, 8, 20.0, 20.0, 7.5, 3.5)
    colour = np.arange(16 * 8 * 3, dtype=np.uint8).reshape(8, 16, 3)
    with RealSenseRecorder(path, width=16, height=8, fps=30, intrinsics=k) as recorder:
        recorder.add(colour, np.full((8, 16), 800, np.uint16), T0)
    for cam in playing(path):
        frame = cam.grab(timeout_s=20.0)
        assert frame.color.shape == (8, 16, 3)
        assert cam.intrinsics is not None
        assert (cam.intrinsics.width, cam.intrinsics.height) == (16, 8)


def test_a_recording_beyond_the_servers_image_size_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from vision_server.process import decoder_limits

    path = tmp_path / "big.db3"
    k = Intrinsics(16, 8, 20.0, 20.0, 7.5, 3.5)
    with RealSenseRecorder(path, width=16, height=8, fps=30, intrinsics=k) as recorder:
        recorder.add(np.zeros((8, 16, 3), np.uint8), np.full((8, 16), 800, np.uint16), T0)
    monkeypatch.setattr(decoder_limits, "loaded_limit", lambda: 100)  # 16x8 = 128 pixels
    for cam in playing(path):
        message = grab_error(cam)
        assert "colour stream is 16x8, more than the server's 100 pixels" in message
