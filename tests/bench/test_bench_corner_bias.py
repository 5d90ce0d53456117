"""The QR pose bench's sensor check takes the corner detector's bias on the code's side from a
measurement against the renderer's truth, not from a constant that went stale when the
detector changed (-0.07 px configured, -0.04 px measured: the fitted depth scale of a perfect
sensor came out 0.04 % high, 0.4 mm at 1 m, the whole of the QR pose goal's tail)."""

from __future__ import annotations

import pytest

from bench.calibration import _corner_bias, _sensor_check


def test_a_perfect_sensor_checked_with_the_measured_bias_reads_true() -> None:
    bias_px, standard_error = _corner_bias(6)
    assert -0.15 < bias_px < 0.0  # corners pulled a little inwards, as on any blurred edge
    assert standard_error < 0.02
    checked = _sensor_check(6, 0, bias_px)
    perfect = checked["noise only"]["registration"]
    assert perfect.scale == pytest.approx(1.0, abs=2e-4)
    systematic = next(rows for label, rows in checked.items() if label != "noise only")
    assert systematic["registration"].scale == pytest.approx(1.005, abs=2e-4)
