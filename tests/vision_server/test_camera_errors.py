"""CAMERA_UNAVAILABLE reaches clients without the server's absolute paths (issue 13, hole 8):
the message names the camera and its files as the configuration wrote them (or by file name
when the configuration gave an absolute path); the server log has the full path."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from loopback import client_for, run

from protocol import CameraUnavailable
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import CellRuntime

CONFIG = """\
server: {{port: 0}}
cameras:
  missing: {{source: folder, path: not_there}}
  absolute: {{source: folder, path: {root}/elsewhere}}
  corrupt: {{source: folder, path: corrupt}}
  escaping: {{source: folder, path: escaping}}
  video: {{source: opencv, device: clips/none.avi, reconnect_interval_s: 60}}
inspections:
  - {{name: on_missing, type: presence, camera: missing, measure: mean_intensity, min: 0}}
"""


def write_cell(root: Path) -> Path:
    # check-config refuses a folder that does not exist: these two vanish after the load.
    for gone in ("not_there", "elsewhere"):
        (root / gone).mkdir()
        cv2.imwrite(str(root / gone / "0.png"), np.zeros((4, 4), np.uint8))
    (root / "corrupt").mkdir()
    (root / "corrupt" / "0.png").write_bytes(b"\x89PNG but not really")
    (root / "secret").mkdir()
    cv2.imwrite(str(root / "secret" / "s.png"), np.zeros((4, 4), np.uint8))
    (root / "escaping").mkdir()
    os.symlink(root / "secret" / "s.png", root / "escaping" / "0.png")
    path = root / "cell.yaml"
    path.write_text(CONFIG.format(root=root), encoding="utf-8")
    return path


EXPECTED = {
    "missing": "folder not_there does not exist",
    "absolute": "folder elsewhere does not exist",
    "corrupt": "cannot decode corrupt/0.png",
    "escaping": "refused escaping/0.png: it resolves outside the folder escaping",
    "video": "video file clips/none.avi does not exist",
}


def test_camera_errors_name_configured_paths_and_log_the_full_ones(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    runtime = CellRuntime(write_cell(tmp_path))
    for gone in ("not_there", "elsewhere"):  # removed while the server runs
        shutil.rmtree(tmp_path / gone)
    messages: dict[str, CameraUnavailable] = {}

    async def body() -> None:
        server = VisionServer(runtime.catalog, ServerSettings(port=0))
        async with server, client_for(server) as client:
            with pytest.raises(CameraUnavailable) as excinfo:
                await client.inspect("on_missing")
            messages["inspect"] = excinfo.value
            for name in EXPECTED:
                with pytest.raises(CameraUnavailable) as excinfo:
                    await client.capture(name)
                messages[name] = excinfo.value

    try:
        with caplog.at_level("WARNING", logger="vision_server.cameras"):
            run(body())
    finally:
        runtime.close()
    for name, expected in EXPECTED.items():
        exc = messages[name]
        assert exc.message.startswith(f"camera {name!r} ("), exc.message
        assert expected in exc.message
        assert exc.details["camera"] == name
    assert EXPECTED["missing"] in messages["inspect"].message
    for exc in messages.values():
        assert str(tmp_path) not in exc.message
        assert str(tmp_path.resolve()) not in exc.message
        assert str(tmp_path) not in str(exc.details)
    assert str(tmp_path / "not_there") in caplog.text, "the log has the full path"
