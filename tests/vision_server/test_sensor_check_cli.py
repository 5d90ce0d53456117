"""``vision-server sensor-check`` on saved views of the simulated, misregistered RGB-D camera:
it reports the shift and scale the simulation applied, and says the sensor needs correcting."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from vision_server.commands import main

from .analysis.conftest import qr_cell, random_view

CELL = """\
cameras:
  rgbd:
    source: request
    depth: true
    intrinsics: {width: 640, height: 480, fx: 570.3, fy: 570.3, cx: 319.5, cy: 239.5}
inspections:
  - {name: qp, type: qr_pose, camera: rgbd, side_m: 0.16}
"""


def _views(tmp_path: Path, n: int, **kw: object) -> list[str]:
    cell = qr_cell(5, **kw)  # type: ignore[arg-type]
    rng = np.random.default_rng(3)
    argv: list[str] = []
    for k in range(n):
        cell.world.base_from_tool = random_view(rng)
        frames = [cell.render("rgbd") for _ in range(5)]
        colour = tmp_path / f"v{k}.png"
        cv2.imwrite(str(colour), frames[0].color)
        depths = []
        for j, f in enumerate(frames):
            d = tmp_path / f"v{k}_d{j}.png"
            cv2.imwrite(str(d), f.depth)
            depths.append(str(d))
        argv += ["--view", str(colour), *depths]
    return argv


def test_sensor_check_reports_the_sensor_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "cell.yaml").write_text(CELL, encoding="utf-8")
    views = _views(tmp_path, 12, misregistration_px=(2.0, 1.0), scale_bias=0.005)
    code = main(["sensor-check", "--config", str(tmp_path / "cell.yaml"), "--json", "qp", *views])
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 1
    assert report["views"] == 12
    assert report["ok"] is False
    assert report["depth_scale"] == pytest.approx(1.005, abs=0.0015)
    np.testing.assert_allclose(report["depth_shift_px"], [2.0, 1.0], atol=0.75)
    assert "depth_shift_px" in report["verdict"]


def test_sensor_check_names_a_wrong_inspection(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "cell.yaml").write_text(CELL, encoding="utf-8")
    code = main(["sensor-check", "--config", str(tmp_path / "cell.yaml"), "nope", "--view", "a"])
    assert code == 2
    assert "'nope' is not a qr_pose with side_m" in capsys.readouterr().out
