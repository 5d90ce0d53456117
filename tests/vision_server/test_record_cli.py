"""``vision-server record`` and the replay of its recordings through the inspections:
``run --recording``, golden cases made from a recording, and the console's try on a frame."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from console_server import TOKEN, Browserless, running_cell

from protocol import CameraUnavailable
from vision_server.cameras import RecordingReader
from vision_server.commands import main
from vision_server.commands.golden import pose_error
from vision_server.config import ServiceSettings
from vision_server.service import CellRuntime, InspectionService, InspectRequest

REPO = Path(__file__).resolve().parents[2]

# A fixed Xtion-like RGB-D camera 0.8 m in front of the station's QR board.
SCENE = """
name: record_cli_test
seed: 3
surfaces:
  - {name: floor, center: [0, 0], height: 0.0, size: [4, 4], color: 90}
boxes:
  - {name: wall, pose: {xyz: [1.0, 0, 0], rpy: [0, 0, 0]}, size: [0.02, 2.0, 2.5], color: 150}
qr_boards:
  - name: qr
    text: "cellvision:station-1"
    side_m: 0.16
    pose: {xyz: [0.989, 0.0, 1.0], rpy: [1.5707963267948966, 0.0, -1.5707963267948966]}
robot:
  world_from_base: {xyz: [0, 0, 0]}
  home: {xyz: [0, 0, 1.0], rpy: [-1.5707963267948966, 0, -1.5707963267948966]}
  workspace: {min: [-2, -2, -1], max: [2, 2, 3]}
cameras:
  - name: rgbd
    model: xtion
    mount: fixed
    pose: {eye: [0.2, 0.05, 1.05], target: [0.989, 0.0, 1.0], up: [0, 0, 1]}
    noise_sigma: 1.0
    depth: {}
"""

CELL = """\
results: {enabled: false}
cameras:
  rgbd: {source: sim, scene: scene.yaml, camera: rgbd}
  shelf: {source: folder, path: shelf, mode: once}
  tool: {source: request}
inspections:
  - {name: pose, type: qr_pose, camera: rgbd, side_m: 0.16, expect: "cellvision:station-1"}
  - {name: bright, type: presence, camera: shelf, measure: mean_intensity, min: 100}
"""


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    (tmp_path / "scene.yaml").write_text(SCENE, encoding="utf-8")
    shelf = tmp_path / "shelf"
    shelf.mkdir()
    for i, level in enumerate((40, 160, 200)):
        image = np.full((48, 64, 3), level, np.uint8)
        image[10:20, 10:30] = (i * 50, 255 - i * 50, 7)
        cv2.imwrite(str(shelf / f"img{i}.png"), image)
    path = tmp_path / "cell.yaml"
    path.write_text(CELL, encoding="utf-8")
    return path


def record(cell: Path, *args: str) -> int:
    return main(["record", "--config", str(cell), *args])


def last_json(out: str) -> dict[str, object]:
    data: dict[str, object] = json.loads(out.strip().splitlines()[-1])
    return data


# ----------------------------------------------------------------------------- record


def test_record_the_sim_rgbd_camera_by_frames(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = cell.parent / "rec"
    assert record(cell, "rgbd", "--out", str(out), "--frames", "6", "--json") == 0
    summary = last_json(capsys.readouterr().out)
    assert summary["frames"] == 6
    assert summary["stopped_by"] == "frames"
    assert summary["ok"] is True
    reader = RecordingReader(out)
    assert len(reader) == 6
    assert reader.complete
    assert reader.has_depth
    assert reader.camera == "rgbd"
    assert reader.source == "sim"
    assert reader.settings["scene"] == "scene.yaml"
    assert reader.intrinsics is not None
    assert (reader.intrinsics.width, reader.intrinsics.height) == (640, 480)
    assert len(reader.config_hash) == 16
    assert summary["bytes"] == reader.bytes
    stamps = [e.timestamp_s for e in reader.entries]
    assert stamps == sorted(stamps)
    frame = reader.read(5)
    assert frame.color.shape == (480, 640, 3)
    assert frame.depth is not None
    assert frame.depth.dtype == np.uint16
    assert int(frame.depth.max()) > 0


def test_record_a_folder_camera_keeps_its_pixels(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = cell.parent / "rec"
    assert record(cell, "shelf", "--out", str(out), "--frames", "3") == 0
    printed = capsys.readouterr().out
    assert "recorded 3 frames of camera 'shelf' (folder)" in printed
    assert "stopped by the frames bound" in printed
    reader = RecordingReader(out)
    assert [e.source for e in reader.entries] == ["img0.png", "img1.png", "img2.png"]
    for i, frame in enumerate(reader):
        original = cv2.imread(str(cell.parent / "shelf" / f"img{i}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(frame.color, original)


def test_record_bounded_by_bytes_and_by_duration(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    by_bytes = cell.parent / "by_bytes"
    assert record(cell, "rgbd", "--out", str(by_bytes), "--max-bytes", "2M", "--json") == 0
    summary = last_json(capsys.readouterr().out)
    assert summary["stopped_by"] == "bytes"
    reader = RecordingReader(by_bytes)
    assert 1 <= len(reader) == summary["frames"]
    assert reader.bytes <= 2 * 1024 * 1024

    by_time = cell.parent / "by_time"
    code = record(cell, "rgbd", "--out", str(by_time), "--duration", "3", "--interval", "0.5")
    assert code == 0
    assert "stopped by the duration bound" in capsys.readouterr().out
    assert len(RecordingReader(by_time)) >= 1


def test_a_camera_that_ends_keeps_what_was_recorded(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A replayed source that runs out (a folder played once) ends the recording: a complete
    one, exit 0, not a camera failure."""
    out = cell.parent / "rec"
    assert record(cell, "shelf", "--out", str(out), "--frames", "5", "--json") == 0
    captured = capsys.readouterr()
    assert "CAMERA_UNAVAILABLE" not in captured.err
    summary = last_json(captured.out)
    assert summary["stopped_by"] == "source ended"
    assert summary["frames"] == 3
    assert summary["ok"] is True
    reader = RecordingReader(out)
    assert len(reader) == 3
    assert reader.complete


def test_usage_errors_exit_2_and_record_nothing(
    cell: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out = cell.parent / "rec"
    monkeypatch.delenv("CELLVISION_CONFIG", raising=False)
    assert main(["record", "rgbd", "--out", str(out)]) == 2
    assert "give --config FILE" in capsys.readouterr().err
    assert record(cell, "nope", "--out", str(out)) == 2
    assert "no camera named 'nope'" in capsys.readouterr().err
    assert record(cell, "tool", "--out", str(out)) == 2
    assert "gets its images with each request" in capsys.readouterr().err
    assert record(cell, "rgbd", "--out", str(out), "--frames", "0") == 2
    assert "expected a positive number" in capsys.readouterr().err
    assert record(cell, "rgbd", "--out", str(out), "--max-bytes", "lots") == 2
    assert not out.exists()
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert record(cell, "rgbd", "--out", str(out), "--frames", "1") == 2
    assert "already exists and is not an empty directory" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]


def test_the_realsense_format_is_the_sdks_own_and_plays_back_through_it(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--format realsense writes pyrealsense2's own recording (software_device + recorder),
    which ``source: realsense`` with ``playback:`` plays through the SDK's pipeline."""
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 (the realsense extra)")
    from vision_server.cameras import RealSenseCamera, RealSenseCameraSettings, make_camera
    from vision_server.config import load_config

    rgbd = load_config(cell).cameras["rgbd"]
    with make_camera("rgbd", rgbd, base_dir=cell.parent) as sim:
        sim_k = sim.intrinsics
    assert sim_k is not None
    db3 = cell.parent / "rec.db3"
    code = record(cell, "rgbd", "--out", str(db3), "--format", "realsense", "--frames", "3")
    assert code == 0, capsys.readouterr()
    assert "recorded 3 frames of camera 'rgbd' (sim)" in capsys.readouterr().out
    assert db3.stat().st_size > 0
    settings = RealSenseCameraSettings(playback=db3, width=sim_k.width, height=sim_k.height)
    with RealSenseCamera("replay", settings, base_dir=cell.parent) as replay:
        frames = []
        ended = ""
        for _ in range(10):
            try:
                frames.append(replay.grab(timeout_s=20.0))
            except CameraUnavailable as exc:
                ended = str(exc)
                break
        k = replay.intrinsics
    assert "ended after" in ended
    # The SDK may lose the first frame of a playback on a loaded machine (realsense.py).
    assert 2 <= len(frames) <= 3
    assert k is not None
    assert (k.width, k.height) == (sim_k.width, sim_k.height)
    assert k.fx == pytest.approx(sim_k.fx, rel=1e-6)
    for frame in frames:
        assert frame.color.shape == (sim_k.height, sim_k.width, 3)
        assert frame.depth is not None
        assert 700 < int(np.median(frame.depth[frame.depth > 0])) < 900  # the board at ~0.8 m
    # The SDK's name for it, or nothing: a .bag is refused before the camera opens; an
    # existing file is not overwritten.
    assert record(cell, "rgbd", "--out", str(cell.parent / "x.bag"), "--format", "realsense") == 2
    assert "is a *.db3 file" in capsys.readouterr().err
    assert record(cell, "rgbd", "--out", str(db3), "--format", "realsense") == 2
    assert "already exists" in capsys.readouterr().err


def test_a_killed_recording_replays_what_it_wrote(cell: Path) -> None:
    out = cell.parent / "rec"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    env["PYTHONPATH"] = str(REPO)
    command = [sys.executable, "-m", "vision_server", "record", "rgbd", "--config", str(cell)]
    proc = subprocess.Popen(
        [*command, "--out", str(out), "--frames", "100000"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 120.0  # a generous limit for a loaded machine
        listed = 0
        while listed < 2:
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            assert time.monotonic() < deadline, "the recording listed no second frame"
            time.sleep(0.05)
            try:
                listed = len(RecordingReader(out))
            except ValueError:
                listed = 0  # not yet created: the manifest is never seen half-written
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        if proc.stderr is not None:
            proc.stderr.close()
    reader = RecordingReader(out)
    assert not reader.complete
    assert len(reader) >= 2
    for frame in reader:  # every listed frame is whole
        assert frame.depth is not None
        assert frame.color.shape == (480, 640, 3)


def test_sigterm_stops_like_ctrl_c_with_a_complete_recording(cell: Path) -> None:
    """What ``timeout`` and ``systemctl stop`` send: the recording is closed (complete, every
    frame listed) and the exit code is 143 (128 + SIGTERM)."""
    out = cell.parent / "rec"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    env["PYTHONPATH"] = str(REPO)
    command = [sys.executable, "-m", "vision_server", "record", "rgbd", "--config", str(cell)]
    proc = subprocess.Popen(
        [*command, "--out", str(out), "--frames", "100000", "--json"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 120.0  # a generous limit for a loaded machine
        listed = 0
        while listed < 2:
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            assert time.monotonic() < deadline, "the recording listed no second frame"
            time.sleep(0.05)
            try:
                listed = len(RecordingReader(out))
            except ValueError:
                listed = 0
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert proc.returncode == 143, stderr.decode()
    assert b"Traceback" not in stderr
    summary = last_json(stdout.decode())
    assert summary["stopped_by"] == "terminated by SIGTERM"
    assert summary["ok"] is False
    reader = RecordingReader(out)
    assert reader.complete
    assert reader.stopped_by == "closed"
    assert len(reader) == summary["frames"]
    assert len(reader) >= 2
    for frame in reader:
        assert frame.depth is not None


def broken_cell(tmp_path: Path) -> Path:
    """A folder camera whose only image does not decode: its first grab fails."""
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "bad.png").write_bytes(b"not a PNG")
    path = tmp_path / "broken.yaml"
    path.write_text(
        "results: {enabled: false}\n"
        "cameras:\n  c: {source: folder, path: broken}\n"
        "inspections:\n  - {name: b, type: presence, camera: c, measure: mean_intensity, "
        "min: 0}\n",
        encoding="utf-8",
    )
    return path


def test_a_failed_recording_of_no_frame_leaves_nothing_and_names_the_camera_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = broken_cell(tmp_path)
    out = tmp_path / "new" / "rec"
    for _ in range(2):  # the same --out again: it was removed
        assert record(config, "c", "--out", str(out), "--frames", "3") == 1
        captured = capsys.readouterr()
        assert not out.exists()
        assert "removed: nothing was recorded" in captured.out
        assert "CAMERA_UNAVAILABLE: camera 'c' (folder): cannot decode" in captured.err
        assert "camera 'c': camera 'c'" not in captured.err
    # An empty directory given for it stays, empty.
    given = tmp_path / "given"
    given.mkdir()
    assert record(config, "c", "--out", str(given), "--json") == 1
    summary = last_json(capsys.readouterr().out)
    assert summary["removed"] is True
    assert summary["frames"] == 0
    assert list(given.iterdir()) == []


# ----------------------------------------------------------------------------- replay


def test_the_documented_example_records_and_replays_station_pose(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """docs/recording.md's first commands, on examples/recording.yaml as shipped (the paths
    under tmp_path instead of the working directory)."""
    config = str(REPO / "examples" / "recording.yaml")
    docs = (REPO / "docs" / "recording.md").read_text(encoding="utf-8")
    assert "vision-server record rgbd --config examples/recording.yaml" in docs
    assert "vision-server run station_pose --config examples/recording.yaml" in docs
    out = tmp_path / "recordings" / "monday"
    assert main(["record", "rgbd", "--config", config, "--out", str(out), "--frames", "10"]) == 0
    capsys.readouterr()
    assert RecordingReader(out).has_depth
    args = ["run", "station_pose", "--config", config, "--recording", str(out), "--json"]
    assert main(args) == 0
    runs = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [r["frame"] for r in runs] == [0, 5]
    assert all(r["verdict"] == "pass" for r in runs)


def serve_once(config: Path, inspection: str) -> dict[str, object]:
    """One inspection through the service on its server camera, as a served INSPECT."""
    runtime = CellRuntime(config)
    service = InspectionService(runtime.catalog, ServiceSettings(workers=1, queue_depth=0))
    try:
        reply = asyncio.run(service.inspect(InspectRequest(inspection)))
        return dict(reply.data)
    finally:
        service.close()
        runtime.close()


def test_run_recording_gives_the_pose_the_camera_gives(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = cell.parent / "rec"
    assert record(cell, "rgbd", "--out", str(out), "--frames", "10") == 0
    capsys.readouterr()
    # qr_pose takes 5 frames (its default): two runs of five.
    assert main(["run", "--config", str(cell), "pose", "--recording", str(out), "--json"]) == 0
    runs = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [r["frame"] for r in runs] == [0, 5]
    assert all(r["verdict"] == "pass" for r in runs)
    assert runs[0]["image"].endswith("frame_000000.png")
    recorded = np.asarray(runs[0]["data"]["camera_from_qr"])

    # The same frames from a camera with source: recording, through the served path: the
    # same pose, exactly.
    replay = cell.parent / "replay.yaml"
    replay.write_text(
        "results: {enabled: false}\n"
        "cameras:\n  replay: {source: recording, path: rec}\n"
        "inspections:\n  - {name: pose, type: qr_pose, camera: replay, side_m: 0.16, "
        'expect: "cellvision:station-1"}\n',
        encoding="utf-8",
    )
    served = serve_once(replay, "pose")
    np.testing.assert_array_equal(np.asarray(served["camera_from_qr"]), recorded)
    assert served["source_files"] == [f"frame_{i:06d}.png" for i in range(5)]

    # The sim camera itself (new sensor noise): the same pose within the golden tolerances.
    live = np.asarray(serve_once(cell, "pose")["camera_from_qr"])
    dt, dr = pose_error(live, recorded)
    assert dt < 0.002
    assert dr < 0.01

    # One run from frame 3, with its overlay.
    overlay = cell.parent / "pose.png"
    code = main(
        ["run", "--config", str(cell), "pose", "--recording", str(out), "--frame", "3"]
        + ["--overlay", str(overlay)]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "frame_000003.png (frame 3): PASS pose on rgbd" in printed
    assert cv2.imread(str(overlay)).shape == (480, 640, 3)


def test_run_recording_usage_errors(cell: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = cell.parent / "rec"
    assert record(cell, "rgbd", "--out", str(out), "--frames", "6") == 0
    capsys.readouterr()
    base = ["run", "--config", str(cell), "pose"]
    assert main([*base, "--recording", str(out), "--frame", "2"]) == 2
    assert "the recording has 6 frames (0..5) and pose takes 5 at a time" in (
        capsys.readouterr().err
    )
    assert main([*base, "--recording", str(cell.parent / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main([*base, "--recording", str(out), "--image", "x.png"]) == 2
    assert main([*base, "--image", "x.png", "--frame", "1"]) == 2
    assert "--frame goes with --recording" in capsys.readouterr().err
    (out / "frame_000000.png").write_bytes(b"not a png")
    assert main([*base, "--recording", str(out), "--json"]) == 2
    assert "frame_000000.png is not a PNG file" in capsys.readouterr().out


def test_golden_cases_from_a_recording_round_trip(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = cell.parent / "rec"
    assert record(cell, "rgbd", "--out", str(out), "--frames", "10") == 0
    case = cell.parent / "cases" / "station_pose"
    made = main(
        ["test-inspections", "--config", str(cell), "--from-recording", str(out)]
        + ["--inspection", "pose", "--out", str(case)]
    )
    assert made == 0, capsys.readouterr()
    capsys.readouterr()
    images = sorted(p.name for p in (case / "images").iterdir())
    assert "frame_000000.png" in images
    assert "frame_000005.depth4.png" in images
    assert len(images) == 12  # two runs: a colour image and five depth frames each
    # The colour file is the recorded one, byte for byte.
    assert (case / "images" / "frame_000005.png").read_bytes() == (
        out / "frame_000005.png"
    ).read_bytes()
    assert 'config: "../../cell.yaml"' in (case / "inspection.yaml").read_text()

    assert main(["test-inspections", str(case), "--json"]) == 0
    report = last_json(capsys.readouterr().out)
    assert report["summary"]["passed"] == 2  # type: ignore[index]
    assert report["summary"]["regressions"] == 0  # type: ignore[index]

    # A case is made in a new folder only.
    again = main(
        ["test-inspections", "--config", str(cell), "--from-recording", str(out)]
        + ["--inspection", "pose", "--out", str(case)]
    )
    assert again == 2
    assert "already exists" in capsys.readouterr().err


def test_golden_from_a_folder_recording_of_a_gray_inspection(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = cell.parent / "rec"
    assert record(cell, "shelf", "--out", str(out), "--frames", "3") == 0
    case = cell.parent / "shelf_case"
    made = main(
        ["test-inspections", "--config", str(cell), "--from-recording", str(out)]
        + ["--inspection", "bright", "--out", str(case), "--frame", "0", "--frame", "2"]
    )
    assert made == 0
    capsys.readouterr()
    expected = (case / "expected.yaml").read_text()
    assert "frame_000000.png:\n    verdict: fail" in expected  # level 40 < min 100
    assert "frame_000002.png:\n    verdict: pass" in expected
    assert "intrinsics" not in (case / "inspection.yaml").read_text()
    assert main(["test-inspections", str(case)]) == 0


# ----------------------------------------------------------------------------- console try


def console_config(cell: Path) -> Path:
    """A console server's configuration beside ``cell``: the recording ``rec`` as a camera."""
    config = cell.parent / "console.yaml"
    config.write_text(
        f"server: {{port: 0, auth_token: {TOKEN}}}\n"
        "console: {enabled: true, port: 0}\n"
        "results: {enabled: false}\n"
        "cameras:\n"
        "  replay: {source: recording, path: rec}\n"
        "  shelf: {source: folder, path: shelf}\n"
        "inspections:\n"
        "  - {name: pose, type: qr_pose, camera: replay, side_m: 0.16, "
        'expect: "cellvision:station-1"}\n'
        "  - {name: bright, type: presence, camera: shelf, measure: mean_intensity, min: 100}\n",
        encoding="utf-8",
    )
    return config


def test_the_console_tries_a_frame_of_a_recording(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = cell.parent / "rec"
    assert record(cell, "rgbd", "--out", str(out), "--frames", "10") == 0
    capsys.readouterr()
    assert main(["run", "--config", str(cell), "pose", "--recording", str(out), "--json"]) == 0
    runs = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    with running_cell(console_config(cell)) as running:
        client = Browserless(running.url)
        assert client.login().status == 200
        # The camera's frame of a sequence is the last one an inspection took: none yet.
        assert client.try_("pose", {"source": "camera"}).status == 404
        tried = client.try_("pose", {"source": "recording", "frame": 5, "overlay": False})
        assert tried.status == 200, tried.body
        body = tried.json()
        assert body["verdict"] == "pass"
        np.testing.assert_array_equal(
            np.asarray(body["data"]["camera_from_qr"]),
            np.asarray(runs[1]["data"]["camera_from_qr"]),
        )
        for spec, words in (
            ({"source": "recording", "frame": 10}, "has 10 frames (0..9), no frame 10"),
            ({"source": "recording", "frame": -1}, "frame must be an integer >= 0"),
            ({"source": "recording", "frame": True}, "frame must be an integer >= 0"),
            ({"source": "recording"}, "frame must be an integer >= 0"),
        ):
            refused = client.try_("pose", spec)
            assert refused.status == 400, spec
            assert words in refused.json()["error"]["message"]
        other = client.try_("bright", {"source": "recording", "frame": 0})
        assert other.status == 400
        assert "is not a recording" in other.json()["error"]["message"]
        # Trying a frame did not move the camera: the cell's next inspection gets frame 0.
        served = asyncio.run_coroutine_threadsafe(
            running.app.service.inspect(InspectRequest("pose")), running.loop
        ).result(60)
        assert served.data["source_files"][0] == "frame_000000.png"
        # The try's front door is the try's: without a session, refused.
        assert (
            Browserless(running.url).try_("pose", {"source": "recording", "frame": 0}).status == 401
        )


@pytest.mark.slow
def test_the_console_page_tries_a_chosen_recording_frame(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The try panel of an inspection on a recording camera starts on "Recording frame"; the
    frame typed in is the one tried."""
    pytest.importorskip("selenium")
    from browser import console_errors, headless_chromium
    from console_pages import sign_in, wait_for
    from selenium.webdriver.common.by import By

    out = cell.parent / "rec"
    assert record(cell, "rgbd", "--out", str(out), "--frames", "10") == 0
    capsys.readouterr()
    with running_cell(console_config(cell)) as running, headless_chromium() as driver:
        sign_in(driver, running, "inspections")
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, "[data-inspection=pose]"),
            "the inspection list",
        )
        driver.find_element(By.CSS_SELECTOR, "[data-inspection=pose]").click()
        choice = driver.find_element(By.CSS_SELECTOR, "input[name=try-source][value=recording]")
        wait_for(driver, lambda d: choice.is_selected(), "the recording frame chosen")
        frame = driver.find_element(By.ID, "try-recording-frame")
        assert frame.is_displayed()
        frame.clear()
        frame.send_keys("7")
        driver.find_element(By.ID, "try-run").click()
        verdict = driver.find_element(By.ID, "try-verdict")
        wait_for(driver, lambda d: verdict.text == "PASS", "the frame's verdict")
        frame.clear()
        frame.send_keys("99")
        driver.find_element(By.ID, "try-run").click()
        error = driver.find_element(By.ID, "try-error")
        wait_for(driver, lambda d: "no frame 99" in error.text, "the server's refusal")
        # An inspection on another camera does not offer it.
        driver.find_element(By.CSS_SELECTOR, "[data-inspection=bright]").click()
        recording_choice = driver.find_element(By.ID, "try-source-recording")
        wait_for(driver, lambda d: not recording_choice.is_displayed(), "no recording choice")
        assert console_errors(driver) == []
