"""Section 3's second table: each tool's compute time at 1024x768 beside a 3x3 box blur
(``cv2.blur``) of the same image, measured in the same run (issue 19's "done when").

Every tool runs on one drawn image (:mod:`.tool_scene`: a plate with holes and a magnet, a
DataMatrix, a Code 128 and a QR code), through ``Inspection.run`` without an overlay, one at a
time in this process: what a server worker computes for one request.
"""

from __future__ import annotations

import functools
import time

import cv2

from .common import RunConfig, Section, Stats, Table, fmt, ratio, time_calls
from .tool_scene import SIZE, TOOLS, scene, write_config


def _box_blur_ms(image: object, repeat: int) -> float:
    times = time_calls(functools.partial(cv2.blur, image, (3, 3)), repeat=repeat, warmup=5)
    return Stats.of(times).p50


def add_tool_table(cfg: RunConfig, section: Section) -> None:
    """Time every tool of :mod:`.tool_scene` and add the table (and ``tool_*`` values) to
    ``section``; a tool that fails to load or raises is listed in ``section.skipped``."""
    from vision_server import InspectionInput
    from vision_server.config import load_config

    image = scene()
    directory = cfg.workdir / "tools"
    directory.mkdir(parents=True, exist_ok=True)
    inspections = {i.name: i for i in load_config(write_config(directory, image)).inspections}
    blur_ms = _box_blur_ms(image, cfg.n(200, 5))
    width, height = SIZE
    table = Table(
        ["tool", "what it does", "verdict", "runs", "p50 ms", "p50 ÷ 3x3 blur"],
        caption=(
            f"Each tool at {width}x{height} on one drawn image (bench/tool_scene.py) beside a "
            f"3x3 box blur (cv2.blur) of that image: {fmt(blur_ms, 3)} ms p50, same run."
        ),
    )
    table.add("3x3 box blur", "cv2.blur, the reference", "—", cfg.n(200, 5), fmt(blur_ms, 3), "1×")
    source = InspectionInput(image)
    for name, what in TOOLS:
        inspection = inspections[name]
        t0 = time.perf_counter()
        try:
            outcome = inspection.run(source, overlay=False)
        except Exception as exc:  # noqa: BLE001 - a tool being rewritten: say so, time the rest
            section.skipped.append(f"tool {name}: raised {type(exc).__name__}: {exc}")
            continue
        first_ms = (time.perf_counter() - t0) * 1000.0
        # about a second of each tool, 5..300 runs (2 in the quick run)
        repeat = cfg.n(int(min(300, max(5, 1000.0 / max(first_ms, 1e-3)))), 2)
        times = time_calls(
            functools.partial(inspection.run, source, overlay=False),
            repeat=repeat,
            warmup=cfg.n(2, 0),
        )
        s = Stats.of(times)
        verdict = "pass" if outcome.passed else "fail"
        shown = fmt(s.p50, 3 if s.p50 < 1.0 else 2)  # a presence check takes ~0.01 ms
        table.add(name, what, verdict, s.n, shown, ratio(s.p50, blur_ms))
        section.value(f"tool_{name}_{width}x{height}_p50_ms", s.p50)
        section.value(f"tool_{name}_{width}x{height}_over_blur3", s.p50 / blur_ms)
    section.value(f"box_blur3_{width}x{height}_ms", blur_ms)
    section.tables.append(table)


__all__ = ["add_tool_table"]
