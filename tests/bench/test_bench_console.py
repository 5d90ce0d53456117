"""The console bench (bench/console.py): its arithmetic on made-up frames, and its smoke run
(``python -m bench --quick --only console``: a real server with the console, a real viewer
process, real protocol clients). No timing is asserted: a smoke run's figures mean nothing."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path
from typing import Any

import pytest

from bench.__main__ import main
from bench.console import live_figures
from bench.console_viewer import frame_interval_s


def test_the_viewer_polls_frames_at_the_pages_rate() -> None:
    # js/cameras.js: min(view_fps or fps or 5, 15) for a server camera, 1 per s for a request one
    assert frame_interval_s({"source": "opencv", "view_fps": 10}) == pytest.approx(0.1)
    assert frame_interval_s({"source": "sim", "view_fps": 60}) == pytest.approx(1 / 15)
    assert frame_interval_s({"source": "sim", "view_fps": None, "fps": None}) == 0.2
    assert frame_interval_s({"source": "request", "view_fps": None}) == 1.0


def test_live_figures_count_distinct_frames_inside_the_window() -> None:
    frames = [
        (99.0, 99.5),  # arrived before the window
        (100.00, 100.01),
        (100.00, 100.11),  # the cached frame again: not a new one
        (100.20, 100.23),
        (float("nan"), 100.5),  # no timestamp header: not counted
        (100.90, 101.5),  # arrived after the window
    ]
    figures = live_figures(frames, 100.0, 101.0)
    assert figures.answers == 3
    assert figures.fps == pytest.approx(2.0)
    assert figures.latencies == pytest.approx([10.0, 110.0, 30.0])


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("aiohttp") is None, reason="no aiohttp: no console")
def test_the_quick_run_measures_throughput_beside_the_closed_console_and_the_live_view(
    tmp_path: Path,
) -> None:
    report = tmp_path / "BENCHMARKS.md"
    status = main(["--quick", "--only", "console", "--report", str(report), "--no-plots"])
    results: dict[str, Any] = json.loads((tmp_path / "bench" / "results.json").read_text())
    section = results["sections"]["console"]
    assert status == 0, section["skipped"]
    values = section["values"]
    for name in ("brightness", "cap_locate"):
        for page in ("closed", "cameras", "server"):
            assert values[f"{name}_{page}_rps"] > 0, values
        for page in ("cameras", "server"):
            assert math.isfinite(values[f"{name}_{page}_over_closed"]), values
    for key in ("idle", "brightness", "cap_locate"):
        assert math.isfinite(values[f"live_{key}_p50_ms"]), values
    assert values["live_idle_fps"] > 0
    assert values["viewer_cameras_requests_per_s"] > 0
    goals = [g["what"] for g in section["goals"]]
    assert sum(">= 0.9x with the console closed" in g for g in goals) == 4
    text = report.read_text()
    assert "capture → arrival p50 ms" in text
    assert "÷ the camera's rate" in text
