"""The folder source: replay order, cycle/once, depth pairing, bad files, confinement."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol import CameraUnavailable
from vision_server.cameras import FolderCamera, FolderCameraSettings, Intrinsics, make_camera
from vision_server.cameras.folder import natural_key

T = 1.0


def write_gray(path: Path, level: int, size: tuple[int, int] = (8, 6)) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((size[1], size[0]), level, np.uint8))
    return path


def write_depth(path: Path, mm: int, size: tuple[int, int] = (8, 6)) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((size[1], size[0]), mm, np.uint16))
    return path


def folder_camera(base: Path, **kwargs: object) -> FolderCamera:
    settings = FolderCameraSettings(**kwargs)  # type: ignore[arg-type]
    camera = make_camera("replay", settings, base_dir=base)
    assert isinstance(camera, FolderCamera)
    camera.open()
    return camera


def levels(camera: FolderCamera, n: int) -> list[int]:
    return [int(camera.grab(timeout_s=T).color[0, 0]) for _ in range(n)]


def test_natural_order_and_cycle(tmp_path: Path) -> None:
    for number, level in ((10, 30), (2, 20), (1, 10)):
        write_gray(tmp_path / "imgs" / f"img{number}.png", level)
    camera = folder_camera(tmp_path, path=Path("imgs"))
    frames = [camera.grab(timeout_s=T) for _ in range(5)]
    assert [int(f.color[0, 0]) for f in frames] == [10, 20, 30, 10, 20]
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert frames[0].color.ndim == 2
    assert frames[0].depth is None
    assert not camera.has_depth
    assert camera.status()["frames"] == 5


def test_cycle_rescans_and_sees_new_files(tmp_path: Path) -> None:
    write_gray(tmp_path / "a.png", 10)
    camera = folder_camera(tmp_path, path=tmp_path)
    assert levels(camera, 1) == [10]
    write_gray(tmp_path / "b.png", 20)
    assert levels(camera, 3) == [10, 20, 10]


def test_once_stops_with_a_clear_error(tmp_path: Path) -> None:
    for i in range(3):
        write_gray(tmp_path / f"{i}.png", 10 * i)
    camera = folder_camera(tmp_path, path=tmp_path, mode="once")
    assert levels(camera, 3) == [0, 10, 20]
    with pytest.raises(CameraUnavailable, match=r"exhausted after 3 images") as excinfo:
        camera.grab(timeout_s=T)
    assert "'replay'" in excinfo.value.message
    status = camera.status()
    assert status["connected"] is False
    assert status["state"] == "ended"
    assert "exhausted" in status["last_error"]


def test_grab_many_gives_distinct_frames(tmp_path: Path) -> None:
    for i in range(2):
        write_gray(tmp_path / f"{i}.png", i)
    camera = folder_camera(tmp_path, path=tmp_path)
    frames = camera.grab_many(4, timeout_s=T)
    assert [f.index for f in frames] == [0, 1, 2, 3]


def test_missing_or_empty_folder_then_it_appears(tmp_path: Path) -> None:
    camera = folder_camera(tmp_path, path=Path("later"))
    with pytest.raises(CameraUnavailable, match="does not exist"):
        camera.grab(timeout_s=T)
    (tmp_path / "later").mkdir()
    with pytest.raises(CameraUnavailable, match=r"no files matching '\*\.png'"):
        camera.grab(timeout_s=T)
    write_gray(tmp_path / "later" / "x.png", 42)
    assert levels(camera, 1) == [42]


def test_corrupt_file_is_named_and_skipped(tmp_path: Path) -> None:
    write_gray(tmp_path / "0.png", 10)
    (tmp_path / "1.png").write_bytes(b"\x89PNG but not really")
    write_gray(tmp_path / "2.png", 30)
    camera = folder_camera(tmp_path, path=tmp_path)
    assert levels(camera, 1) == [10]
    with pytest.raises(CameraUnavailable, match=r"cannot decode .*1\.png"):
        camera.grab(timeout_s=T)
    assert levels(camera, 1) == [30]


def test_symlink_outside_the_folder_is_refused(tmp_path: Path) -> None:
    outside = write_gray(tmp_path / "secret" / "outside.png", 99)
    folder = tmp_path / "replay"
    write_gray(folder / "0.png", 10)
    os.symlink(outside, folder / "1.png")
    os.symlink(folder / "0.png", folder / "2.png")  # inside: allowed
    camera = folder_camera(tmp_path, path=folder)
    assert levels(camera, 1) == [10]
    with pytest.raises(CameraUnavailable, match=r"refused .*1\.png.*outside the folder"):
        camera.grab(timeout_s=T)
    assert levels(camera, 1) == [10]


def test_color_modes(tmp_path: Path) -> None:
    bgra = np.zeros((6, 8, 4), np.uint8)
    bgra[..., 0], bgra[..., 2], bgra[..., 3] = 200, 50, 128
    assert cv2.imwrite(str(tmp_path / "c.png"), bgra)
    unchanged = folder_camera(tmp_path, path=tmp_path).grab(timeout_s=T).color
    assert unchanged.shape == (6, 8, 3)
    assert tuple(unchanged[0, 0]) == (200, 0, 50)
    gray = folder_camera(tmp_path, path=tmp_path, color="gray").grab(timeout_s=T).color
    assert gray.shape == (6, 8)
    write_gray(tmp_path / "g" / "g.png", 77)
    bgr = folder_camera(tmp_path, path=tmp_path / "g", color="bgr").grab(timeout_s=T).color
    assert bgr.shape == (6, 8, 3)


def test_sixteen_bit_colour_needs_a_conversion_mode(tmp_path: Path) -> None:
    write_depth(tmp_path / "wide.png", 1000)
    camera = folder_camera(tmp_path, path=tmp_path)
    with pytest.raises(CameraUnavailable, match=r"wide\.png.*8-bit"):
        camera.grab(timeout_s=T)


def test_depth_paired_by_stem(tmp_path: Path) -> None:
    for i, stem in enumerate(("b", "a")):
        write_gray(tmp_path / "color" / f"{stem}.png", 10 + i)
        write_depth(tmp_path / "depth" / f"{stem}.png", 1000 + i)
    camera = folder_camera(tmp_path, path=tmp_path, glob="color/*.png", depth_glob="depth/*.png")
    assert camera.has_depth
    first = camera.grab(timeout_s=T)
    assert first.depth is not None
    assert first.depth.dtype == np.uint16
    assert (int(first.color[0, 0]), int(first.depth[0, 0])) == (11, 1001)  # a
    second = camera.grab(timeout_s=T)
    assert second.depth is not None
    assert (int(second.color[0, 0]), int(second.depth[0, 0])) == (10, 1000)  # b


def test_depth_paired_by_order_and_excluded_from_colour(tmp_path: Path) -> None:
    write_gray(tmp_path / "0001_color.png", 10)
    write_gray(tmp_path / "0002_color.png", 20)
    write_depth(tmp_path / "0001_depth.png", 500)
    write_depth(tmp_path / "0002_depth.png", 600)
    camera = folder_camera(tmp_path, path=tmp_path, glob="*.png", depth_glob="*_depth.png")
    frames = camera.grab_many(3, timeout_s=T)
    pairs = [(int(f.color[0, 0]), int(f.depth[0, 0])) for f in frames if f.depth is not None]
    assert pairs == [(10, 500), (20, 600), (10, 500)]


def test_depth_count_mismatch_and_bad_depth(tmp_path: Path) -> None:
    write_gray(tmp_path / "c1.png", 10)
    write_gray(tmp_path / "c2.png", 20)
    write_depth(tmp_path / "d" / "x.png", 500)
    camera = folder_camera(tmp_path, path=tmp_path, glob="c*.png", depth_glob="d/*.png")
    with pytest.raises(CameraUnavailable, match="2 images .* but 1 depth images"):
        camera.grab(timeout_s=T)

    write_gray(tmp_path / "e" / "c1.png", 10)
    write_gray(tmp_path / "e" / "d" / "c1.png", 10)  # 8-bit "depth"
    camera = folder_camera(tmp_path, path=tmp_path / "e", depth_glob="d/*.png")
    with pytest.raises(CameraUnavailable, match="uint16"):
        camera.grab(timeout_s=T)

    write_gray(tmp_path / "f" / "c1.png", 10)
    write_depth(tmp_path / "f" / "d" / "c1.png", 500, size=(4, 3))
    camera = folder_camera(tmp_path, path=tmp_path / "f", depth_glob="d/*.png")
    with pytest.raises(CameraUnavailable, match="differs from the colour image"):
        camera.grab(timeout_s=T)


def test_images_that_do_not_fit_the_intrinsics_are_refused(tmp_path: Path) -> None:
    write_gray(tmp_path / "a.png", 1, size=(8, 6))
    intrinsics = Intrinsics(16, 12, 20.0, 20.0, 7.5, 5.5)
    camera = folder_camera(tmp_path, path=tmp_path, intrinsics=intrinsics)
    assert camera.intrinsics == intrinsics
    with pytest.raises(CameraUnavailable, match=r"a\.png: the image is 8x6 .* for 16x12"):
        camera.grab(timeout_s=T)


def test_closed_camera_refuses(tmp_path: Path) -> None:
    write_gray(tmp_path / "a.png", 1)
    camera = folder_camera(tmp_path, path=tmp_path)
    camera.close()
    camera.close()
    with pytest.raises(CameraUnavailable, match="closed"):
        camera.grab(timeout_s=T)


def test_natural_key() -> None:
    names = ["img10.png", "img2.png", "img1.png", "a.png"]
    assert sorted(names, key=natural_key) == ["a.png", "img1.png", "img2.png", "img10.png"]
