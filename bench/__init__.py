"""cellvision's benchmarks (issue #7): ``python -m bench`` (``make bench``) measures the
protocol and server against references taken in the same run and writes docs/BENCHMARKS.md
with plots in docs/bench/.

One module per measurement, each with ``NAME``, ``TITLE`` and ``run(cfg, env) -> Section``,
in the report's order (``SECTIONS``). ``--quick`` runs all of them with tiny sizes (the smoke
test in tests/bench/). Benchmarks never assert timings.
"""

from __future__ import annotations

from types import ModuleType

from . import (
    anomaly,
    calibration,
    caliper,
    camera_aravis,
    compute,
    console,
    hand_eye,
    intrinsics,
    latency,
    line,
    locate_blur,
    locate_template,
    mixed,
    mqtt,
    pick,
    plant,
    qr_real,
    render,
    results_page,
    throughput,
    workers,
)

SECTIONS: tuple[ModuleType, ...] = (
    latency,
    throughput,
    workers,
    mixed,
    console,
    line,
    mqtt,
    compute,
    calibration,
    intrinsics,
    hand_eye,
    pick,
    qr_real,
    render,
    results_page,
    locate_blur,
    caliper,
    locate_template,
    camera_aravis,
    anomaly,
    plant,
)

__all__ = ["SECTIONS"]
