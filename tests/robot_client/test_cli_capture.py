"""``robot-client capture``: raw frames of a server camera saved as lossless PNG files, as a user
runs it (a subprocess against a live server)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
from loopback import server_in_thread

from vision_server import Catalog
from vision_server.cameras import (
    FolderCamera,
    FolderCameraSettings,
    RequestCamera,
    RequestCameraSettings,
)
from vision_server.service.builtin import MeanIntensityPresence

ROOT = Path(__file__).resolve().parents[2]


def robot_client(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "robot_client.commands.program", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


def test_capture_writes_the_cameras_frames_as_they_were(tmp_path: Path) -> None:
    folder = tmp_path / "replay"
    folder.mkdir()
    images = [np.full((30, 40, 3), value, np.uint8) for value in (10, 20, 30)]
    for i, image in enumerate(images):
        image[0, 0] = (i, 255 - i, 7)  # not flat: a lossy path would change it
        cv2.imwrite(str(folder / f"img{i}.png"), image)
    catalog = Catalog.build(
        [
            RequestCamera("tool", RequestCameraSettings()),
            FolderCamera("line", FolderCameraSettings(folder), base_dir=tmp_path),
        ],
        [MeanIntensityPresence("brightness", "tool", 64.0, 255.0)],
    )
    out = tmp_path / "out"
    out.mkdir()
    with server_in_thread(catalog) as server:
        address = f"127.0.0.1:{server.port}"
        done = robot_client("--server", address, "capture", "line", "-n", "2", "--out", str(out))
        assert done.returncode == 0, done.stderr
        written = sorted(out.iterdir())
        assert [p.name for p in written] == ["line-000-color.png", "line-001-color.png"]
        for path, image in zip(written, images, strict=False):
            assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), image)
        as_json = robot_client("--server", address, "--json", "capture", "line", "--out", str(out))
        assert as_json.returncode == 0, as_json.stderr
        assert json.loads(as_json.stdout)["files"][0]["role"] == "color"
        # No folder is created unasked: a usage error before anything is sent.
        missing = robot_client("--server", address, "capture", "line", "--out", str(tmp_path / "x"))
        assert missing.returncode == 2
        assert "no such folder" in missing.stderr
        assert not (tmp_path / "x").exists()
        unknown = robot_client(
            "--server", address, "--json", "capture", "nosuch", "--out", str(out)
        )
        assert unknown.returncode == 4
        assert json.loads(unknown.stdout)["error"]["code"] == "UNKNOWN_CAMERA"
