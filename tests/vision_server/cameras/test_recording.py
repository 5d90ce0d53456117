"""Recordings: the format written and read back exactly, the bounds, an interrupted recording,
bad recordings as typed errors, and the ``recording`` source replaying one as a camera."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol import CameraUnavailable
from vision_server.cameras import (
    RECORDING_MANIFEST,
    FolderCameraSettings,
    Intrinsics,
    ManualClock,
    OpenCVCameraSettings,
    RecordingCamera,
    RecordingCameraSettings,
    RecordingError,
    RecordingReader,
    RecordingWriter,
    SimCameraSettings,
    make_camera,
    public_settings,
)
from vision_server.cameras import recording as recording_module
from vision_server.config import ConfigError, load_config

T = 5.0

# A small fixed RGB-D camera over a bright cap (the sim source's test scene, trimmed).
SCENE = """
name: recording_test
seed: 1
background: 0
light: {direction: [0, 0, -1], ambient: 0.2, diffuse: 0.8}
surfaces:
  - {name: belt, center: [0, 0], height: 0.5, size: [2, 2], color: 20}
parts:
  - {name: cap, type: rotor_cap, at: [0.0, 0.0], support: belt, radius: 0.03, height: 0.025,
     color: 220}
robot:
  world_from_base: {xyz: [0, 0, 0]}
  home: {xyz: [0, 0, 0.8], rpy: [3.141592653589793, 0, 0]}
  workspace: {min: [-1, -1, 0], max: [1, 1, 1.5]}
cameras:
  - name: rgbd
    mount: fixed
    pose: {xyz: [0, 0, 1.3], rpy: [3.141592653589793, 0, 0]}
    intrinsics: {width: 160, height: 120, fx: 150, fy: 150, cx: 79.5, cy: 59.5,
                 dist: [0.0, 0.0, 0.0, 0.0, 0.0]}
    channels: 3
    noise_sigma: 1.0
    vignetting: 0
    depth: {}
"""

K = Intrinsics(8, 6, 10.0, 10.0, 3.5, 2.5)


def writer(path: Path, **kwargs: object) -> RecordingWriter:
    options: dict[str, object] = {"camera": "cam", "source": "test", "intrinsics": K}
    options.update(kwargs)
    return RecordingWriter(path, **options)  # type: ignore[arg-type]


def gray(level: int) -> np.ndarray:
    return np.full((6, 8), level, np.uint8)


def record_levels(path: Path, levels: list[int], **kwargs: object) -> None:
    with writer(path, **kwargs) as w:
        for i, level in enumerate(levels):
            assert w.add(gray(level), np.full((6, 8), 1000 + level, np.uint16), timestamp_s=i)


# ----------------------------------------------------------------------------- round trip


def test_a_sim_rgbd_recording_replays_exactly(tmp_path: Path) -> None:
    (tmp_path / "scene.yaml").write_text(SCENE, encoding="utf-8")
    sim = make_camera("top", SimCameraSettings(Path("scene.yaml"), "rgbd"), base_dir=tmp_path)
    sim.open()
    grabbed = sim.grab_many(4, timeout_s=T)
    sim.close()
    settings = SimCameraSettings(Path("scene.yaml"), "rgbd")
    with RecordingWriter(
        tmp_path / "rec",
        camera="top",
        source="sim",
        settings=public_settings(settings),
        intrinsics=sim.intrinsics,
        config_hash="abc123",
    ) as w:
        for frame in grabbed:
            assert w.add(frame.color, frame.depth, timestamp_s=frame.timestamp)

    reader = RecordingReader(tmp_path / "rec")
    assert (reader.camera, reader.source, reader.config_hash) == ("top", "sim", "abc123")
    assert reader.complete
    assert reader.stopped_by == "closed"
    assert reader.intrinsics == sim.intrinsics
    assert reader.settings["scene"] == "scene.yaml"
    assert len(reader) == 4
    assert reader.has_depth
    for frame, back in zip(grabbed, reader, strict=True):
        assert back.color.dtype == np.uint8
        assert back.color.shape == (120, 160, 3)
        np.testing.assert_array_equal(back.color, frame.color)
        assert back.depth is not None
        assert frame.depth is not None
        np.testing.assert_array_equal(back.depth, frame.depth)
        assert back.entry.timestamp_s == frame.timestamp

    camera = make_camera("replay", RecordingCameraSettings(Path("rec")), base_dir=tmp_path)
    assert isinstance(camera, RecordingCamera)
    camera.open()
    assert camera.has_depth
    assert camera.intrinsics == sim.intrinsics
    assert camera.sequence
    assert not camera.view_takes_frames
    for i, frame in enumerate(grabbed):
        replayed = camera.grab(timeout_s=T)
        np.testing.assert_array_equal(replayed.color, frame.color)
        assert replayed.depth is not None
        assert frame.depth is not None
        np.testing.assert_array_equal(replayed.depth, frame.depth)
        assert replayed.timestamp == frame.timestamp
        assert replayed.index == i
        assert replayed.source == f"frame_{i:06d}.png"
    with pytest.raises(CameraUnavailable, match=r"recording rec ended after 4 frames"):
        camera.grab(timeout_s=T)
    assert camera.status()["state"] == "ended"
    camera.close()


def test_gray_bgr_and_16_bit_colour_keep_their_layout(tmp_path: Path) -> None:
    images = [
        np.arange(48, dtype=np.uint8).reshape(6, 8),
        np.arange(144, dtype=np.uint8).reshape(6, 8, 3),
        (np.arange(48, dtype=np.uint16) * 1300).reshape(6, 8),
    ]
    with writer(tmp_path / "rec", intrinsics=None) as w:
        for i, image in enumerate(images):
            assert w.add(image, timestamp_s=100.0 + i)
    reader = RecordingReader(tmp_path / "rec")
    assert [e.color_format for e in reader.entries] == ["gray8", "bgr8", "gray16"]
    assert not reader.has_depth
    for image, back in zip(images, reader, strict=True):
        assert back.color.dtype == image.dtype
        np.testing.assert_array_equal(back.color, image)
        assert back.depth is None
    # The camera gives 16-bit gray as the inspections take it: 8-bit, scaled.
    camera = make_camera("r", RecordingCameraSettings(tmp_path / "rec"), base_dir=tmp_path)
    colours = [camera.grab(timeout_s=T).color for _ in images]
    np.testing.assert_array_equal(colours[2], np.rint(images[2] / 256.0).astype(np.uint8))
    with pytest.raises(RecordingError, match="8-bit gray or BGR, or 16-bit gray"):
        writer(tmp_path / "other").add(np.zeros((6, 8), np.float32), timestamp_s=0.0)


def test_a_folder_camera_recording_has_the_files_pixels(tmp_path: Path) -> None:
    folder = tmp_path / "shots"
    folder.mkdir()
    originals = []
    for i in range(3):
        image = np.random.default_rng(i).integers(0, 255, (6, 8, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / f"img{i}.png"), image)
        originals.append(image)
    settings = FolderCameraSettings(Path("shots"))
    camera = make_camera("shelf", settings, base_dir=tmp_path)
    with writer(tmp_path / "rec", settings=public_settings(settings), intrinsics=None) as w:
        for _ in range(3):
            frame = camera.grab(timeout_s=T)
            assert w.add(frame.color, frame.depth, timestamp_s=frame.timestamp, source=frame.source)
    reader = RecordingReader(tmp_path / "rec")
    assert [e.source for e in reader.entries] == ["img0.png", "img1.png", "img2.png"]
    assert reader.settings == {
        "path": "shots",
        "glob": "*.png",
        "mode": "cycle",
        "color": "unchanged",
    }
    for original, back in zip(originals, reader, strict=True):
        np.testing.assert_array_equal(back.color, original)


def test_settings_are_shown_as_to_clients(tmp_path: Path) -> None:
    absolute = public_settings(FolderCameraSettings(tmp_path / "secret" / "shots"))
    assert absolute["path"] == "shots"
    stream = public_settings(OpenCVCameraSettings("rtsp://admin:hunter2@10.0.0.5/stream"))
    assert "hunter2" not in json.dumps(stream)
    assert stream["device"] == "rtsp://admin:***@10.0.0.5/stream"
    with_k = public_settings(FolderCameraSettings(Path("f"), intrinsics=K))
    assert with_k["intrinsics"]["distortion"] == [0.0] * 5


# ----------------------------------------------------------------------------- bounds


def test_max_frames_stops_cleanly(tmp_path: Path) -> None:
    w = writer(tmp_path / "rec", max_frames=2)
    assert w.add(gray(1), timestamp_s=0.0)
    assert w.add(gray(2), timestamp_s=1.0)
    assert w.stopped
    assert w.stopped_by == "frames"
    assert not w.add(gray(3), timestamp_s=2.0)
    w.close()
    reader = RecordingReader(tmp_path / "rec")
    assert len(reader) == 2
    assert reader.stopped_by == "frames"
    assert reader.complete
    assert not (tmp_path / "rec" / "frame_000002.png").exists()


def test_max_bytes_keeps_the_files_within_the_bound(tmp_path: Path) -> None:
    noise = [
        np.random.default_rng(i).integers(0, 255, (60, 80, 3), dtype=np.uint8) for i in range(5)
    ]
    one = len(cv2.imencode(".png", noise[0], [cv2.IMWRITE_PNG_COMPRESSION, 1])[1])
    w = writer(tmp_path / "rec", intrinsics=None, max_bytes=int(one * 2.5))
    written = [w.add(image, timestamp_s=float(i)) for i, image in enumerate(noise)]
    assert written == [True, True, False, False, False]
    assert w.stopped_by == "bytes"
    w.close()
    reader = RecordingReader(tmp_path / "rec")
    assert len(reader) == 2
    on_disk = sum((tmp_path / "rec" / e.color).stat().st_size for e in reader.entries)
    assert on_disk == reader.bytes <= int(one * 2.5)


def test_max_duration_on_the_writers_clock(tmp_path: Path) -> None:
    clock = ManualClock()
    w = writer(tmp_path / "rec", max_duration_s=2.0, clock=clock)
    assert w.add(gray(1), timestamp_s=0.0)
    clock.advance(1.5)
    assert w.add(gray(2), timestamp_s=1.5)
    assert not w.stopped
    clock.advance(0.5)
    assert w.stopped
    assert w.stopped_by == "duration"
    assert not w.add(gray(3), timestamp_s=2.0)
    w.close()
    assert len(RecordingReader(tmp_path / "rec")) == 2


def test_bad_bounds_and_a_used_directory_are_refused(tmp_path: Path) -> None:
    for bound in ({"max_frames": 0}, {"max_bytes": -1}, {"max_duration_s": float("nan")}):
        with pytest.raises(ValueError, match="max_"):
            writer(tmp_path / "a", **bound)
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "x.txt").write_text("x")
    with pytest.raises(RecordingError, match="already exists and is not an empty directory"):
        writer(tmp_path / "used")


# ----------------------------------------------------------------------------- interrupted


def test_an_unclosed_recording_replays_what_its_manifest_lists(tmp_path: Path) -> None:
    clock = ManualClock()
    w = writer(tmp_path / "rec", clock=clock)  # manifest at most once a second
    for i in range(3):
        clock.advance(1.0)
        assert w.add(gray(i), timestamp_s=float(i))  # a second since the last: synced
    w.add(gray(9), timestamp_s=9.0)  # written, but the manifest was synced a moment ago
    # No close: as if the process was killed here.
    reader = RecordingReader(tmp_path / "rec")
    assert not reader.complete
    assert reader.stopped_by is None
    assert len(reader) == 3  # the fourth frame's file exists, its entry is not yet synced
    assert [int(f.color[0, 0]) for f in reader] == [0, 1, 2]
    assert (tmp_path / "rec" / "frame_000003.png").exists()
    leftovers = [p.name for p in (tmp_path / "rec").iterdir() if p.name.endswith(".tmp")]
    assert leftovers == []


def test_an_empty_recording_is_valid_and_its_camera_says_so(tmp_path: Path) -> None:
    writer(tmp_path / "rec")  # killed before its first frame
    assert len(RecordingReader(tmp_path / "rec")) == 0
    camera = make_camera("r", RecordingCameraSettings(Path("rec")), base_dir=tmp_path)
    with pytest.raises(CameraUnavailable, match="recording rec has no frames"):
        camera.grab(timeout_s=T)


# ----------------------------------------------------------------------------- bad recordings


def manifest(path: Path) -> dict[str, object]:
    data: dict[str, object] = json.loads((path / RECORDING_MANIFEST).read_text())
    return data


def rewrite(path: Path, **changes: object) -> None:
    data = manifest(path)
    data.update(changes)
    (path / RECORDING_MANIFEST).write_text(json.dumps(data))


def test_bad_manifests_are_typed_errors_naming_the_cause(tmp_path: Path) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10, 20])
    good = manifest(rec)
    frame0 = good["frames"][0]  # type: ignore[index]

    def refused(match: str, **changes: object) -> None:
        (rec / RECORDING_MANIFEST).write_text(json.dumps({**good, **changes}))
        with pytest.raises(RecordingError, match=match):
            RecordingReader(rec)

    with pytest.raises(RecordingError, match="does not exist"):
        RecordingReader(tmp_path / "nope")
    refused("version 2; this server reads version 1", version=2)
    refused("format is 'something-else'", format="something-else")
    refused(r"frames\[0\]: a 1000000000x6 image", frames=[{**frame0, "width": 10**9}])
    refused(r"frames\[0\]: index is 5", frames=[{**frame0, "index": 5}])
    refused("color must be a PNG file name", frames=[{**frame0, "color": "../../etc/x.png"}])
    refused("color_format must be one of", frames=[{**frame0, "color_format": "rgb48"}])
    refused("timestamp_s must be a number", frames=[{**frame0, "timestamp_s": "noon"}])
    refused("intrinsics", intrinsics={"width": -1})
    refused(
        "frame 0 is 8x6 but the intrinsics are for 9x6",
        intrinsics={**good["intrinsics"], "width": 9},
    )  # type: ignore[dict-item]
    (rec / RECORDING_MANIFEST).write_text("{not json")
    with pytest.raises(RecordingError, match="not valid JSON"):
        RecordingReader(rec)
    (rec / RECORDING_MANIFEST).unlink()
    with pytest.raises(RecordingError, match="has no recording.json"):
        RecordingReader(rec)


def test_absurd_sizes_are_refused_before_parsing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10, 20, 30])
    monkeypatch.setattr(recording_module, "MAX_FRAMES", 2)
    with pytest.raises(RecordingError, match="3 frames, more than a recording holds"):
        RecordingReader(rec)
    monkeypatch.setattr(recording_module, "MAX_MANIFEST_BYTES", 100)
    with pytest.raises(RecordingError, match="bytes, more than a recording's manifest"):
        RecordingReader(rec)


def test_bad_frame_files_are_typed_errors_and_the_camera_names_them(tmp_path: Path) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10, 20, 30, 40, 50])
    (rec / "frame_000001.png").unlink()
    (rec / "frame_000002.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    cv2.imwrite(str(rec / "frame_000003.png"), np.zeros((7, 8), np.uint8))  # another size
    png = (rec / "frame_000004.png").read_bytes()
    (rec / "frame_000004.png").write_bytes(png[:40])  # a right header, the data cut
    reader = RecordingReader(rec)
    np.testing.assert_array_equal(reader.read(0).color, gray(10))
    with pytest.raises(RecordingError, match=r"frame_000001.png is missing \(frame 1"):
        reader.read(1)
    with pytest.raises(RecordingError, match="frame_000002.png is not a PNG file"):
        reader.read(2)
    with pytest.raises(RecordingError, match="the PNG is 8x7, 8-bit.*manifest says 8x6 gray8"):
        reader.read(3)
    with pytest.raises(RecordingError, match="frame_000004.png cannot be decoded"):
        reader.read(4)
    with pytest.raises(RecordingError, match="no frame 5"):
        reader.read(5)

    camera = make_camera("r", RecordingCameraSettings(Path("rec")), base_dir=tmp_path)
    assert camera.grab(timeout_s=T).color[0, 0] == 10
    with pytest.raises(CameraUnavailable) as missing:
        camera.grab(timeout_s=T)
    # The client sees the recording as configured (relative), not the server's path.
    assert "rec/frame_000001.png is missing" in missing.value.message
    assert str(tmp_path) not in missing.value.message


def test_an_oversized_frame_file_is_refused_before_reading(tmp_path: Path) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10])
    with (rec / "frame_000000.png").open("ab") as file:
        file.write(b"\0" * 200_000)
    with pytest.raises(RecordingError, match="more than a 8x6 gray8 PNG can have"):
        RecordingReader(rec).read(0)


@pytest.mark.skipif(not hasattr(os, "symlink"), reason="no symlinks")
def test_a_frame_file_linking_outside_is_refused(tmp_path: Path) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10])
    outside = tmp_path / "outside.png"
    (rec / "frame_000000.png").rename(outside)
    (rec / "frame_000000.png").symlink_to(outside)
    with pytest.raises(RecordingError, match="resolves outside the recording"):
        RecordingReader(rec).read(0)


def _drop_intrinsics(rec: Path, width: int, height: int, layout: str) -> None:
    data = manifest(rec)
    frames = data["frames"]
    assert isinstance(frames, list)
    frames[0] = {**frames[0], "width": width, "height": height, "color_format": layout}
    rewrite(rec, intrinsics=None, frames=frames)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
def test_a_manifest_that_is_not_a_regular_file_is_refused_without_reading(
    tmp_path: Path,
) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10])
    (rec / RECORDING_MANIFEST).unlink()
    os.mkfifo(rec / RECORDING_MANIFEST)  # opening it to read would block; reading, wait
    with pytest.raises(RecordingError, match=r"recording.json: it is a FIFO \(named pipe\)"):
        RecordingReader(rec)
    (rec / RECORDING_MANIFEST).unlink()
    (rec / RECORDING_MANIFEST).mkdir()
    with pytest.raises(RecordingError, match="recording.json: it is a directory"):
        RecordingReader(rec)
    (rec / RECORDING_MANIFEST).rmdir()
    # A device inside the recording (bound in, say): /dev/zero would read without end.
    (rec / RECORDING_MANIFEST).symlink_to("/dev/zero")
    with pytest.raises(RecordingError, match="resolves outside the recording"):
        RecordingReader(rec)


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
def test_a_device_as_the_manifest_is_refused_by_what_it_is(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The descriptor's type is checked, not only where the path leads: a device the
    # directory holds (it cannot be made here without privileges) is stood in for by
    # /dev/zero opened in the manifest's place.
    rec = tmp_path / "rec"
    record_levels(rec, [10])
    real_open = os.open
    opened: list[int] = []

    def open_zero(path: object, flags: int, *args: object) -> int:
        if str(path).endswith(RECORDING_MANIFEST):
            opened.append(flags)
            return real_open("/dev/zero", flags)
        return real_open(path, flags, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(recording_module.os, "open", open_zero)
    with pytest.raises(RecordingError, match="recording.json: it is a character device"):
        RecordingReader(rec)
    assert opened
    assert opened[0] & os.O_NONBLOCK  # a FIFO would not block the open


def test_a_manifest_longer_than_its_size_said_is_cut_at_the_limit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10])
    size = (rec / RECORDING_MANIFEST).stat().st_size
    real_fstat = os.fstat

    def small_fstat(descriptor: int) -> os.stat_result:  # a file that grows while read
        info = real_fstat(descriptor)
        return os.stat_result((info.st_mode, *info[1:6], 0, *info[7:]))

    monkeypatch.setattr(recording_module.os, "fstat", small_fstat)
    monkeypatch.setattr(recording_module, "MAX_MANIFEST_BYTES", size - 1)
    with pytest.raises(RecordingError, match="has more than a recording's manifest can have"):
        RecordingReader(rec)


@pytest.mark.skipif(not hasattr(os, "symlink"), reason="no symlinks")
def test_a_manifest_linking_outside_is_refused_and_one_inside_is_read(tmp_path: Path) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10])
    (rec / RECORDING_MANIFEST).rename(rec / "kept.json")
    (rec / RECORDING_MANIFEST).symlink_to("kept.json")
    assert len(RecordingReader(rec)) == 1
    (rec / RECORDING_MANIFEST).unlink()
    (rec / "kept.json").rename(tmp_path / "outside.json")
    (rec / RECORDING_MANIFEST).symlink_to(tmp_path / "outside.json")
    with pytest.raises(RecordingError, match="recording.json: it resolves outside"):
        RecordingReader(rec)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
def test_a_fifo_or_a_directory_as_a_frame_file_is_unavailable_not_a_stall(
    tmp_path: Path,
) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10, 20, 30])
    (rec / "frame_000001.png").unlink()
    os.mkfifo(rec / "frame_000001.png")  # no writer: a blocking open or read never returns
    (rec / "frame_000002.depth.png").unlink()
    (rec / "frame_000002.depth.png").mkdir()
    reader = RecordingReader(rec)
    with pytest.raises(RecordingError, match=r"frame_000001.png: it is a FIFO"):
        reader.read(1)
    with pytest.raises(RecordingError, match=r"frame_000002.depth.png: it is a directory"):
        reader.read(2)
    camera = make_camera("r", RecordingCameraSettings(Path("rec")), base_dir=tmp_path)
    assert camera.grab(timeout_s=T).color[0, 0] == 10
    with pytest.raises(CameraUnavailable, match=r"rec/frame_000001.png: it is a FIFO"):
        camera.grab(timeout_s=T)
    with pytest.raises(CameraUnavailable, match=r"rec/frame_000002.depth.png: it is a dir"):
        camera.frame_at(2)


@pytest.mark.parametrize(("side", "layout"), [(32768, "gray8"), (20000, "bgr8")])
def test_a_frame_over_the_pixel_limit_is_refused_when_the_manifest_is_read(
    tmp_path: Path, side: int, layout: str
) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10])
    _drop_intrinsics(rec, side, side, layout)
    limit = recording_module.max_pixels()
    assert side * side > limit
    message = rf"frame 0 is {side}x{side}, more than {limit} pixels"
    with pytest.raises(RecordingError, match=message):
        RecordingReader(rec)
    # The configuration refuses it when loaded (check-config), not at the first grab.
    with pytest.raises(ConfigError, match=message):
        load_config(write_cell(tmp_path, "{source: recording, path: rec}"))
    with pytest.raises(RecordingError, match="more than .* pixels"):
        writer(tmp_path / "big").add(np.zeros((side, side), np.uint8), timestamp_s=0.0)


def test_any_decode_failure_is_a_typed_error_naming_the_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = tmp_path / "rec"
    record_levels(rec, [10, 20])

    def refuse(data: object, flags: int) -> None:
        raise cv2.error("OpenCV(5.0) loadsave.cpp: error: (-215) pixels <= CV_IO_MAX_IMAGE_PIXELS")

    camera = make_camera("r", RecordingCameraSettings(Path("rec")), base_dir=tmp_path)
    monkeypatch.setattr(recording_module.cv2, "imdecode", refuse)
    with pytest.raises(RecordingError, match=r"frame_000000.png cannot be decoded \(frame 0\)"):
        RecordingReader(rec).read(0)
    with pytest.raises(CameraUnavailable, match=r"rec/frame_000000.png cannot be decoded"):
        camera.grab(timeout_s=T)
    with pytest.raises(CameraUnavailable, match=r"frame_000001.png cannot be decoded"):
        camera.frame_at(1)


# ----------------------------------------------------------------------------- the camera


def test_loop_intrinsics_and_frame_at(tmp_path: Path) -> None:
    record_levels(tmp_path / "rec", [10, 20, 30])
    own = Intrinsics(8, 6, 12.0, 12.0, 4.0, 3.0)
    camera = make_camera(
        "r", RecordingCameraSettings(Path("rec"), loop=True, intrinsics=own), base_dir=tmp_path
    )
    assert isinstance(camera, RecordingCamera)
    assert camera.intrinsics == own  # the configuration's over the recording's
    frames = [camera.grab(timeout_s=T) for _ in range(7)]
    assert [int(f.color[0, 0]) for f in frames] == [10, 20, 30, 10, 20, 30, 10]
    assert [f.index for f in frames] == list(range(7))  # the counter keeps rising
    assert [f.timestamp for f in frames] == [0.0, 1.0, 2.0, 0.0, 1.0, 2.0, 0.0]
    # frame_at reads any frame and leaves the position where it was.
    assert int(camera.frame_at(2).color[0, 0]) == 30
    assert int(camera.grab(timeout_s=T).color[0, 0]) == 20
    with pytest.raises(RecordingError, match="no frame 3"):
        camera.frame_at(3)
    assert camera.status()["loops"] == 2
    camera.close()
    with pytest.raises(CameraUnavailable, match="closed"):
        camera.grab(timeout_s=T)


def test_intrinsics_of_another_size_make_the_camera_unavailable(tmp_path: Path) -> None:
    record_levels(tmp_path / "rec", [10])
    other = Intrinsics(16, 12, 12.0, 12.0, 8.0, 6.0)
    camera = make_camera(
        "r", RecordingCameraSettings(Path("rec"), intrinsics=other), base_dir=tmp_path
    )
    with pytest.raises(
        CameraUnavailable, match="the image is 8x6 but the intrinsics are for 16x12"
    ):
        camera.grab(timeout_s=T)


def test_a_recording_that_appears_later_is_read_at_the_next_grab(tmp_path: Path) -> None:
    camera = make_camera("r", RecordingCameraSettings(Path("later")), base_dir=tmp_path)
    with pytest.raises(CameraUnavailable, match="recording later does not exist"):
        camera.grab(timeout_s=T)
    record_levels(tmp_path / "later", [42])
    assert int(camera.grab(timeout_s=T).color[0, 0]) == 42


# ----------------------------------------------------------------------------- configuration


def write_cell(tmp_path: Path, camera: str) -> Path:
    path = tmp_path / "cell.yaml"
    path.write_text(
        "results: {enabled: false}\n"
        f"cameras:\n  replay: {camera}\n"
        "inspections:\n  - {name: bright, type: presence, camera: replay, measure: mean_intensity, "
        "min: 0}\n",
        encoding="utf-8",
    )
    return path


def test_the_configuration_checks_the_recording(tmp_path: Path) -> None:
    record_levels(tmp_path / "rec", [10, 20])
    config = load_config(write_cell(tmp_path, "{source: recording, path: rec, loop: true}"))
    settings = config.cameras["replay"]
    assert settings == RecordingCameraSettings(Path("rec"), loop=True)

    with pytest.raises(
        ConfigError, match=r"cameras -> replay -> path: recording .*missing does not exist"
    ):
        load_config(write_cell(tmp_path, "{source: recording, path: missing}"))
    writer(tmp_path / "empty")
    with pytest.raises(ConfigError, match="has no frames"):
        load_config(write_cell(tmp_path, "{source: recording, path: empty}"))
    with pytest.raises(ConfigError, match="recording are 8x6|frames are 8x6"):
        load_config(
            write_cell(
                tmp_path,
                "{source: recording, path: rec, intrinsics: {width: 16, height: 12, fx: 1, "
                "fy: 1, cx: 8, cy: 6}}",
            )
        )
    with pytest.raises(ConfigError, match="loop"):
        load_config(write_cell(tmp_path, "{source: recording, path: rec, loop: 3}"))
    with pytest.raises(ConfigError, match="speed"):
        load_config(write_cell(tmp_path, "{source: recording, path: rec, speed: 2}"))
