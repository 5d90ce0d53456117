"""The anomaly bench section (bench/anomaly.py): its network guard refuses and records, then
restores; its smoke run measures both methods against the reference and states the goals.
No figure is asserted (a smoke run's figures mean nothing)."""

from __future__ import annotations

import json
import math
import socket
from pathlib import Path

import pytest

from bench.__main__ import main
from bench.anomaly import _no_network

pytestmark = pytest.mark.slow


def test_the_network_guard_refuses_records_and_restores() -> None:
    attempts: list[str] = []
    with _no_network(attempts):
        with pytest.raises(OSError, match="refused by the bench"):
            socket.getaddrinfo("example.org", 80)
        with socket.socket() as sock, pytest.raises(OSError, match="refused by the bench"):
            sock.connect(("127.0.0.1", 9))
    assert len(attempts) == 2
    with socket.socket() as server:  # restored: a loopback connection works again
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        with socket.create_connection(server.getsockname(), timeout=5):
            pass


def test_the_quick_section_measures_both_methods_against_the_reference(tmp_path: Path) -> None:
    report = tmp_path / "BENCHMARKS.md"
    status = main(
        ["--quick", "--only", "anomaly", "--report", str(report), "--plots-dir", str(tmp_path)]
    )
    assert status == 0
    section = json.loads((tmp_path / "results.json").read_text())["sections"]["anomaly"]
    values = section["values"]
    for key in ("variation_n10_mean_auroc", "variation_n10_ms_p50", "variation_n10_miss"):
        assert values[key] is not None, key
        assert math.isfinite(values[key]), key
    weights_missing = any("method patches" in reason for reason in section["skipped"])
    if not weights_missing:
        assert math.isfinite(values["patches_n10_mean_auroc"])
        assert any("patches, from 10 good images" in g["what"] for g in section["goals"])
    assert values["network_attempts"] == 0
    assert 0.0 <= values["variation_n10_baseline_mean_auroc"] <= 1.0
    text = report.read_text()
    assert "Image AUROC per part" in text
    assert "error vs baseline" in text
