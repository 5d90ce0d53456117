"""The benchmarks' smoke run (``python -m bench --quick``), so that the benchmark code cannot
rot: every section runs with tiny sizes and produces numbers. No timing is asserted here (the
figures of a smoke run mean nothing). The report and plots go to a temporary directory."""

from __future__ import annotations

import importlib
import json
import math
from pathlib import Path
from typing import Any

import pytest

from bench import SECTIONS
from bench.__main__ import main
from bench.qr_real import data_dir

pytestmark = pytest.mark.slow


def _importable(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return True


HAVE_AIOHTTP = _importable("aiohttp")
HAVE_MATPLOTLIB = _importable("matplotlib")
PLOTTED = {m.NAME for m in SECTIONS}  # every section draws one figure


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("bench")
    report = out / "BENCHMARKS.md"
    plots = out / "bench"
    status = main(["--quick", "--report", str(report), "--plots-dir", str(plots)])
    results = json.loads((plots / "results.json").read_text())
    return {"status": status, "report": report, "plots": plots, "results": results}


def test_the_quick_run_finishes_without_a_crash(run: dict[str, Any]) -> None:
    crashed = {
        name: s["skipped"]
        for name, s in run["results"]["sections"].items()
        if any(r.startswith("crashed") for r in s["skipped"])
    }
    assert run["status"] == 0, crashed
    assert run["results"]["quick"] is True


@pytest.mark.parametrize("name", [m.NAME for m in SECTIONS])
def test_every_section_produced_numbers(run: dict[str, Any], name: str) -> None:
    section = run["results"]["sections"][name]
    if name == "qr_real" and not (data_dir() / "manifest.json").is_file():
        pytest.skip(f"the real QR photographs are not at {data_dir()} (set CELLVISION_QR_REAL)")
    values = section["values"]
    assert values, f"section {name} measured nothing: {section['skipped']}"
    finite = [v for v in values.values() if v is not None and math.isfinite(v)]
    assert finite, f"section {name} has no finite figure: {values}"


def test_the_report_names_every_section_and_the_machine(run: dict[str, Any]) -> None:
    text = run["report"].read_text()
    assert "Smoke run" in text
    for module in SECTIONS:
        assert f"## {module.TITLE}" in text
    for key in ("cpu", "cores", "python", "numpy", "opencv", "date"):
        assert f"| {key} |" in text


def test_goals_are_reported_with_their_figures(run: dict[str, Any]) -> None:
    goals = [g for s in run["results"]["sections"].values() for g in s["goals"]]
    assert goals
    for goal in goals:
        assert goal["figure"]
        assert isinstance(goal["met"], bool)


def _finite(values: dict[str, Any], key: str) -> bool:
    value = values.get(key)
    return value is not None and math.isfinite(value)


def _goal_names(run: dict[str, Any], section: str) -> list[str]:
    return [g["what"] for g in run["results"]["sections"][section]["goals"]]


def test_throughput_is_set_beside_the_machines_limit(run: dict[str, Any]) -> None:
    values = run["results"]["sections"]["throughput"]["values"]
    for name in ("brightness", "cap_locate"):
        assert _finite(values, f"{name}_limit_rps"), values
        assert _finite(values, f"{name}_c2_d2_p99_over_queue"), values
        assert _finite(values, f"{name}_c2_d2_busy_per_answer"), values
    goals = " ".join(_goal_names(run, "throughput"))
    assert "machine's limit" in goals
    assert "no collapse" in goals
    assert "grows no faster than the queue" in goals
    assert "single-client" not in goals  # the former goal is information now


def test_the_worker_model_is_chosen_per_inspection(run: dict[str, Any]) -> None:
    values = run["results"]["sections"]["workers"]["values"]
    for name in ("brightness", "cap_locate", "station_pose"):
        assert _finite(values, f"{name}_thread_scaling"), values
        assert values[f"{name}_threads"] in (0.0, 1.0)
    assert "chosen" in run["report"].read_text()


def test_mixed_load_compares_the_cheap_inspections_p99(run: dict[str, Any]) -> None:
    values = run["results"]["sections"]["mixed"]["values"]
    for key in ("cheap_idle_p99_ms", "cheap_loaded_p99_ms", "cheap_p99_ratio", "expensive_rps"):
        assert _finite(values, key), values
    assert any("<= 3x its idle p99" in g for g in _goal_names(run, "mixed"))


def test_latency_measures_the_large_images_and_says_how_copies_are_counted(
    run: dict[str, Any],
) -> None:
    values = run["results"]["sections"]["latency"]["values"]
    for key in ("inspect_large1_cellvision_p50_ms", "inspect_large2_cellvision_p50_ms"):
        assert _finite(values, key), values
    goals = " ".join(_goal_names(run, "latency"))
    assert "<= 0.3 ms p50 at 1024x768" in goals
    assert "1.3x the floor's p99" in goals
    text = run["report"].read_text()
    assert "4096x3000 gray8" in text
    assert "12-bit in depth16" in text
    assert "Copies of the image per request" in text


@pytest.mark.skipif(
    not HAVE_AIOHTTP, reason="aiohttp (bench extra) not installed: no HTTP/JSON reference"
)
def test_the_http_reference_was_measured(run: dict[str, Any]) -> None:
    values = run["results"]["sections"]["latency"]["values"]
    assert math.isfinite(values["inspect_http_p50_ms"])
    assert math.isfinite(values["http_over_cellvision_p50"])


@pytest.mark.skipif(HAVE_AIOHTTP, reason="aiohttp is installed: the HTTP reference runs")
def test_without_aiohttp_the_http_reference_is_skipped_with_a_reason(run: dict[str, Any]) -> None:
    skipped = run["results"]["sections"]["latency"]["skipped"]
    assert any("HTTP/JSON reference" in reason for reason in skipped)


@pytest.mark.skipif(not HAVE_MATPLOTLIB, reason="matplotlib (bench extra) not installed: no plots")
def test_plots_are_written_and_linked(run: dict[str, Any]) -> None:
    text = run["report"].read_text()
    plots: Path = run["plots"]
    for name, section in run["results"]["sections"].items():
        if name not in PLOTTED or not section["values"]:
            continue
        assert section["plots"], f"section {name} drew nothing"
        for file in section["plots"]:
            assert (plots / file).stat().st_size > 1000
            assert f"bench/{file}" in text


@pytest.mark.skipif(HAVE_MATPLOTLIB, reason="matplotlib is installed: the plots are drawn")
def test_without_matplotlib_the_plots_are_skipped_with_a_reason(run: dict[str, Any]) -> None:
    for section in run["results"]["sections"].values():
        assert not section["plots"]
    assert any(
        "matplotlib" in reason
        for section in run["results"]["sections"].values()
        for reason in section["skipped"]
    )
