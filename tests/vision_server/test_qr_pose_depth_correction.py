"""The qr_pose inspection's sensor-error keys (issue 18 part 3): depth_scale and depth_shift_px
from the YAML reach the analysis, and a depth that disagrees with the printed side warns."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from geometry import invert_transform
from vision_server import InspectionInput
from vision_server.config import ConfigError, load_config

from .analysis.conftest import qr_cell, random_view

CELL = """\
cameras:
  rgbd:
    source: request
    depth: true
    intrinsics: {{width: 640, height: 480, fx: 570.3, fy: 570.3, cx: 319.5, cy: 239.5}}
inspections:
  - {{name: qp, type: qr_pose, camera: rgbd, side_m: 0.16{extra}}}
"""


def _inspection(tmp_path: Path, extra: str = "") -> Any:
    path = tmp_path / "cell.yaml"
    path.write_text(CELL.format(extra=extra), encoding="utf-8")
    config = load_config(path)
    return next(i for i in config.inspections if i.common.name == "qp"), config


def _frame() -> tuple[Any, InspectionInput, Any]:
    cell = qr_cell(5, misregistration_px=(2.0, 1.0), scale_bias=0.01)
    cell.world.base_from_tool = random_view(np.random.default_rng(11))
    frames = [cell.render("rgbd") for _ in range(5)]
    return frames[0], frames[0].color, tuple(f.depth for f in frames)


def test_correction_from_the_yaml_and_the_warning(tmp_path: Path) -> None:
    frame, color, depth = _frame()
    truth = frame.truth.qr_codes["qr"].camera_from_qr
    errors = {}
    for label, extra in {
        # the depth's own distance (the unchecked fusion off: without a check the printed
        # code's module grid would already take the distance to ~0.1 mm)
        "raw": ", unchecked_scale_std: 0, unchecked_shift_std_px: 0",
        "corrected": ", depth_scale: 1.01, depth_shift_px: [2, 1], max_depth_vs_side: 0.004, "
        "depth_scale_std: 0.0001, depth_shift_std_px: [0.25, 0.25], corner_bias_px: -0.03",
    }.items():
        inspection, config = _inspection(tmp_path, extra)
        intr = config.cameras["rgbd"].intrinsics
        outcome = inspection.run(InspectionInput(color, depth, intr), overlay=False)
        q = outcome.data["quality"]
        pose = np.asarray(outcome.data["camera_from_qr"])
        errors[label] = float(np.linalg.norm((invert_transform(truth) @ pose)[:3, 3]))
        assert len(q["shift_sensitivity"]) == 2
        assert q["side_px"] > 50
        if label == "raw":
            assert q["depth_vs_side"] > 0.005  # 1 % scale error, seen against the board
            assert "sensor-check" in q["warnings"][0]
        else:
            assert abs(q["depth_vs_side"]) < 0.004
            assert q["warnings"] == []
        assert outcome.passed  # a warning does not fail the inspection
    assert errors["corrected"] < 0.5 * errors["raw"]


def test_bad_correction_keys_are_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="depth_shift_px"):
        _inspection(tmp_path, ", depth_shift_px: [1]")
    with pytest.raises(ConfigError, match="depth_scale"):
        _inspection(tmp_path, ", depth_scale: 0")
    with pytest.raises(ConfigError, match=r"corner_bias_px.*within \+/-1 px"):
        _inspection(tmp_path, ", corner_bias_px: 5")


def test_unchecked_sensor_keys_are_validated_and_named(tmp_path: Path) -> None:
    inspection, _ = _inspection(tmp_path)
    assert (inspection.unchecked_scale_std, inspection.unchecked_shift_std_px) == (0.01, 2.0)
    assert inspection.corner_bias_px is None  # not measured unless configured
    inspection, _ = _inspection(tmp_path, ", unchecked_scale_std: 0.005, unchecked_shift_std_px: 3")
    assert (inspection.unchecked_scale_std, inspection.unchecked_shift_std_px) == (0.005, 3.0)
    with pytest.raises(ConfigError, match=r"unchecked_scale_std.*0.01 = 1 %"):
        _inspection(tmp_path, ", unchecked_scale_std: 1")  # 1 for 1 %: a typo
    with pytest.raises(ConfigError, match="unchecked_shift_std_px"):
        _inspection(tmp_path, ", unchecked_shift_std_px: -2")
