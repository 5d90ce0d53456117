"""10. Calipers and measurement in millimetres: edge position error on rendered bars (pixel
frame, exact answer), width and diameter errors in mm through the tool camera's lens model at
its working distance, and the compute time of a caliper's measurements on a 1024x768 image
beside a 3x3 box blur (``cv2.blur``) of the same image in the same run."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .common import Goal, RunConfig, Section, Table, fmt
from .env import Env
from .plots import pyplot, save

NAME = "caliper"
TITLE = "10. Calipers and measurement in millimetres"

BLURS = (0.7, 1.0, 1.5, 2.0)
WORKING_DISTANCE_MM = 350.0  # the tool camera above the caps (examples/scenes/grundfos_cell.yaml)


def _bar(centre: tuple[float, float], width: float, angle: float, blur: float, seed: int) -> Any:
    """A bright bar on a dark ground, 8x supersampled, blurred, camera noise 1.5 grey."""
    w, h, s = 128, 96, 8
    ys, xs = np.mgrid[0 : h * s, 0 : w * s].astype(np.float64)
    xs, ys = (xs + 0.5) / s - 0.5, (ys + 0.5) / s - 0.5
    along = (xs - centre[0]) * math.cos(angle) + (ys - centre[1]) * math.sin(angle)
    cover = cv2.resize(
        (np.abs(along) <= width / 2).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA
    ).astype(np.float64)
    image = cv2.GaussianBlur(60.0 + 130.0 * cover, (0, 0), blur)
    image = image + np.random.default_rng(seed).normal(0.0, 1.5, image.shape)
    return np.asarray(np.clip(np.rint(image), 0, 255), np.uint8)


def _edge_errors(seeds: int, blur: float) -> list[float]:
    from vision_server.analysis import Band, find_edges

    errors: list[float] = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        centre = (float(rng.uniform(60, 68)), float(rng.uniform(44, 52)))
        angle, width = float(rng.uniform(-0.5, 0.5)), float(rng.uniform(20, 40))
        tilt = float(rng.uniform(-0.1, 0.1))
        edges = find_edges(
            _bar(centre, width, angle, blur, seed),
            Band(*centre, 80, 9, angle + tilt),
            min_strength=10,
        )
        half = width / 2 / math.cos(tilt)
        if len(edges) != 2:
            errors += [math.inf, math.inf]
            continue
        errors += [abs(edges[0].offset - (40 - half)), abs(edges[1].offset - (40 + half))]
    return errors


def _mm_errors(seeds: int) -> tuple[list[float], list[float]]:
    from simulation.flat_parts import bar, disc, plane_point, render_flat_part
    from simulation.scene import camera_preset
    from vision_server.analysis import Band, CircleSpec, PlaneUnits, WidthSpec, measure

    camera, _, _ = camera_preset("dmk31bf03")
    units = PlaneUnits(camera, WORKING_DISTANCE_MM)
    widths: list[float] = []
    diameters: list[float] = []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        u, v = float(rng.uniform(120, 900)), float(rng.uniform(120, 650))
        centre = plane_point(camera, WORKING_DISTANCE_MM, (u, v))
        window = (int(u) - 40, int(v) - 40, 80, 80)
        blur = float(rng.uniform(0.6, 1.5))
        angle, width = float(rng.uniform(-0.6, 0.6)), float(rng.uniform(6, 12))
        image = render_flat_part(
            camera, WORKING_DISTANCE_MM, bar(centre, width, angle), window,
            blur_sigma_px=blur, seed=seed,
        )  # fmt: skip
        (got,) = measure(image, [WidthSpec("w", Band(u, v, 70, 9, angle))], units=units)
        widths.append(abs(got.value - width))
        diameter = float(rng.uniform(8, 14))
        image = render_flat_part(
            camera, WORKING_DISTANCE_MM, disc(centre, diameter), window,
            blur_sigma_px=blur, seed=seed,
        )  # fmt: skip
        spec = CircleSpec(
            "d",
            u + float(rng.uniform(-2, 2)),
            v + float(rng.uniform(-2, 2)),
            diameter / 2 / units.mm_per_px,
            search=8,
            polarity="light_to_dark",
        )
        (got,) = measure(image, [spec], units=units)
        diameters.append(abs(got.value - diameter))
    return widths, diameters


def _timing(repeats: int) -> tuple[float, float, NDArray[np.uint8]]:
    """Median ms of a caliper (a width, a 32-ray circle, an 8-strip line) and of cv2.blur
    3x3, on one 1024x768 image."""
    from vision_server.analysis import Band, CircleSpec, LineSpec, Spec, WidthSpec, measure

    rng = np.random.default_rng(5)
    image = np.asarray(np.clip(60 + rng.normal(0, 2, (768, 1024)), 0, 255), np.uint8)
    cv2.rectangle(image, (300, 200), (700, 560), 190, -1)
    cv2.circle(image, (500, 380), 60, 60, -1)
    specs: list[Spec] = [
        WidthSpec("width", Band(500, 250, 500, 15)),
        CircleSpec("hole", 500, 380, 60, search=8, polarity="dark_to_light"),
        LineSpec("top", Band(500, 200, 40, 200, math.pi / 2), polarity="dark_to_light"),
    ]
    caliper_ms: list[float] = []
    blur_ms: list[float] = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        measure(image, specs)
        caliper_ms.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        cv2.blur(image, (3, 3))
        blur_ms.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(caliper_ms)), float(np.median(blur_ms)), image


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    seeds = 6 if cfg.quick else 60
    blurs = BLURS[1:2] if cfg.quick else BLURS

    edges = Table(
        ["blur sigma px", "edges", "error median px", "p95 px", "max px"],
        caption=f"Edge position, rendered bars ({seeds} images, 2 edges each, 128x96, 8x "
        "supersampled, noise 1.5 grey, contrast 130, band 9 px wide tilted up to 0.1 rad):",
    )
    all_errors: list[float] = []
    medians: list[float] = []
    for blur in blurs:
        errors = _edge_errors(seeds, blur)
        all_errors += errors
        medians.append(float(np.median(errors)))
        edges.add(
            fmt(blur, 1),
            len(errors),
            fmt(float(np.median(errors))),
            fmt(float(np.percentile(errors, 95))),
            fmt(max(errors)),
        )
        section.value(f"edge_s{blur:g}_median_px", float(np.median(errors)))
    section.tables.append(edges)
    overall = float(np.median(all_errors))
    section.value("edge_median_px", overall)
    section.goals.append(
        Goal(
            "edge position error median <= 0.05 px (rendered parts, known geometry)",
            f"median {overall:.3f} px over {len(all_errors)} edges",
            overall <= 0.05,
        )
    )

    widths, diameters = _mm_errors(seeds)
    mm = Table(
        ["measurement", "parts", "error median mm", "p95 mm", "max mm"],
        caption=f"In millimetres through the tool camera (1024x768, fx 1400 px, barrel "
        f"distortion) at {WORKING_DISTANCE_MM:g} mm, 0.25 mm per px: bars 6..12 mm and discs "
        "8..14 mm anywhere in the image, blur sigma 0.6..1.5 px, 6x supersampled through the "
        "lens model:",
    )
    for label, errors in (("width", widths), ("diameter", diameters)):
        mm.add(
            label,
            len(errors),
            fmt(float(np.median(errors)), 4),
            fmt(float(np.percentile(errors, 95)), 4),
            fmt(max(errors), 4),
        )
        section.value(f"{label}_p95_mm", float(np.percentile(errors, 95)))
    section.tables.append(mm)
    p95 = float(np.percentile(widths, 95))
    section.goals.append(
        Goal(
            "width error p95 <= 0.02 mm at the tool camera's resolution",
            f"p95 {p95:.4f} mm ({p95 / 0.25:.3f} px) over {len(widths)} bars",
            p95 <= 0.02,
        )
    )

    caliper_ms, blur_ms, _ = _timing(20 if cfg.quick else 200)
    section.value("caliper_ms", caliper_ms)
    section.value("blur3x3_ms", blur_ms)
    timing = Table(
        ["what", "ms (median)", "x blur 3x3"],
        caption="Compute on one 1024x768 gray image, same run:",
    )
    timing.add("caliper: width (500 px band, 15 wide) + circle (32 rays) + line (8 strips)",
               fmt(caliper_ms, 3), fmt(caliper_ms / blur_ms, 1))  # fmt: skip
    timing.add("cv2.blur 3x3", fmt(blur_ms, 3), "1.0")
    section.tables.append(timing)
    section.intro = (
        "vision_server.analysis.measure with its defaults (smoothing 1 px, min_strength 5). "
        "The held-out check on a real photograph (scikit-image's coins against diameters "
        "measured by hand) is a test: tests/vision_server/analysis/test_caliper.py."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.plot(list(blurs), medians, marker="o", label="edge error median")
        ax.axhline(0.05, color="grey", linestyle="--", label="goal 0.05 px")
        ax.set_xlabel("blur sigma [px]")
        ax.set_ylabel("edge position error [px]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        return [save(fig, directory / "caliper.png")]

    section.plot = plot
    return section
