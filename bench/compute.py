"""3. Compute time per inspection type at 1024x768 and 640x480: ``Inspection.run`` of the
configured inspections (what a server worker runs for one request, without the protocol),
in this process, one at a time.

Images: the simulated tool camera over the conveyor (``locate``), the QC camera (``presence``)
and the RGB-D camera at the station (``qr``, ``qr_pose`` with 5 depth frames), each rendered
at its camera's own size and resized to the other size (depth: nearest neighbour); the
inspections at the other size use scaled intrinsics (bench/cell.py). The reference is a 5x5
Gaussian blur of an image of the same size, measured in the same run.

A second table (:mod:`.compute_tools`) times each tool at 1024x768 on one drawn image (locate:
circle, blob, template; presence; code: DataMatrix, Code 128; qr; caliper; a job chaining them)
beside a 3x3 box blur of that image.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any

from .cell import SIZES, require, resized
from .common import RunConfig, Section, Stats, Table, fmt, ratio, time_calls, yardstick_ms
from .compute_tools import add_tool_table
from .env import Env
from .plots import log_scale_if_positive, pyplot, save

NAME = "compute"
TITLE = "3. Compute time per inspection type"
FRAME_30FPS_MS = 1000.0 / 30.0
# (inspection in examples/cell.yaml, which sample image, what it does)
CASES = (
    ("cap_locate", "tool", "locate, circle method (rotor caps)"),
    ("magnet_check", "qc", "presence, dark fraction in an ROI"),
    ("station_qr", "rgbd", "qr: decode + corner order + sub-pixel corners"),
    ("station_pose", "rgbd", "qr_pose, plane method, 5 depth frames"),
    ("station_pose_corners", "rgbd", "qr_pose, corners method (paper), 5 depth frames"),
)


def _budget_repeat(first_ms: float, budget_ms: float, lo: int, hi: int) -> int:
    return int(min(hi, max(lo, budget_ms / max(first_ms, 1e-3))))


def run(cfg: RunConfig, env: Env) -> Section:
    from vision_server import InspectionInput

    section = Section(NAME, TITLE)
    catalog = env.catalog
    require(catalog, *[f"{name}-{w}x{h}" for name, _, _ in CASES for w, h in SIZES])
    samples = env.samples
    table = Table(
        [
            "inspection",
            "type / method",
            "size",
            "verdict",
            "runs",
            "p50 ms",
            "p99 ms",
            "p50 ÷ blur",
            "p50 ÷ 30 fps frame",
        ]
    )
    blur = {size: yardstick_ms((size[1], size[0]), repeat=cfg.n(50, 3)) for size in SIZES}
    results: dict[tuple[str, tuple[int, int]], list[float]] = {}
    for name, source, what in CASES:
        for width, height in SIZES:
            inspection = catalog.catalog.inspection(f"{name}-{width}x{height}")
            camera = catalog.catalog.camera(inspection.camera)
            color = resized(getattr(samples, source), width, height)
            depth: tuple[Any, ...] = ()
            if inspection.uses_depth:
                depth = tuple(resized(d, width, height, depth=True) for d in samples.depth)
            image = InspectionInput(color, depth, getattr(camera, "intrinsics", None))
            t0 = time.perf_counter()
            try:
                outcome = inspection.run(image, overlay=False)
            except Exception as exc:  # noqa: BLE001 - an inspection being rewritten: say so
                section.skipped.append(
                    f"{name} at {width}x{height}: the inspection raised {type(exc).__name__}: {exc}"
                )
                continue
            first_ms = (time.perf_counter() - t0) * 1000.0
            repeat = cfg.n(_budget_repeat(first_ms, 1500.0, 5, 200), 2)
            times = time_calls(
                functools.partial(inspection.run, image, overlay=False),
                repeat=repeat,
                warmup=cfg.n(2, 0),
            )
            results[(name, (width, height))] = times
            s = Stats.of(times)
            verdict = "pass" if outcome.passed else "fail"
            table.add(
                name,
                what,
                f"{width}x{height}",
                verdict,
                s.n,
                fmt(s.p50, 2),
                fmt(s.p99, 2),
                ratio(s.p50, blur[(width, height)]),
                ratio(s.p50, FRAME_30FPS_MS),
            )
            section.value(f"{name}_{width}x{height}_p50_ms", s.p50)
            section.value(f"{name}_{width}x{height}_p99_ms", s.p99)
    for (width, height), ms in blur.items():
        section.value(f"blur_{width}x{height}_ms", ms)
    section.intro = (
        "Inspections of examples/cell.yaml (copies per size: bench/cell.py). "
        + "; ".join(f"blur {w}x{h}: {fmt(ms, 3)} ms" for (w, h), ms in blur.items())
        + ". A fail verdict means the inspection ran to its end and judged (the time is still "
        "the time it takes)."
    )
    section.tables.append(table)
    add_tool_table(cfg, section)

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(8, 3.8))
        names = [c[0] for c in CASES]
        width_bar = 0.38
        for k, size in enumerate(SIZES):
            p50 = [Stats.of(results.get((n, size), [])).p50 for n in names]
            xs = [i + (k - 0.5) * width_bar for i in range(len(names))]
            ax.bar(xs, p50, width_bar, label=f"{size[0]}x{size[1]}")
        ax.set_xticks(range(len(names)), names, rotation=15)
        ax.set_ylabel("compute p50 [ms]")
        log_scale_if_positive(ax)
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
        return [save(fig, directory / "compute.png")]

    section.plot = plot
    return section
