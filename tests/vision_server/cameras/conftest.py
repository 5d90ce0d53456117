"""Helpers for the camera tests: small video files and images written by the tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

WIDTH, HEIGHT = 160, 120


def frame_level(number: int) -> int:
    """The grey level that encodes frame ``number`` (0..109) in a test video."""
    return 10 + 2 * number


def frame_number(image: np.ndarray) -> int:
    """Decode the frame number written by :func:`write_video` (MJPG keeps a flat mean)."""
    return round((float(image.mean()) - 10.0) / 2.0)


def write_video(path: Path, frames: int, *, fps: float = 30.0) -> Path:
    """A WIDTH x HEIGHT MJPG video whose frame i is flat grey ``frame_level(i)``.

    Written under a temporary name and renamed, so that a reader never sees half a file.
    """
    assert frames <= 110
    tmp = path.with_name(f".tmp-{path.name}")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter.fourcc(*"MJPG"), fps, (WIDTH, HEIGHT))
    assert writer.isOpened(), "OpenCV cannot write MJPG/AVI here"
    for i in range(frames):
        writer.write(np.full((HEIGHT, WIDTH, 3), frame_level(i), np.uint8))
    writer.release()
    tmp.replace(path)
    return path


@pytest.fixture
def video(tmp_path: Path) -> Path:
    """A 3 s video at 30 fps."""
    return write_video(tmp_path / "clip.avi", 90)
