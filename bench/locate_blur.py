"""9. Circle locate through real optics: parts found and centre error against defocus blur
(Gaussian sigma 0..4 px) at full and 40 % contrast, on rendered discs (exact answer) and on
scikit-image's coins photograph (the sharp image's answer, the image moved by a known sub-pixel
amount), false reports on scikit-image's unrelated photographs, and the compute time of
:func:`vision_server.analysis.locate.locate_circles` per image."""

from __future__ import annotations

import importlib.util
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

NAME = "locate_blur"
TITLE = "9. Circle locate through blur and dim light"

SIGMAS = (0.0, 1.0, 2.0, 3.0, 4.0)
GAINS = (1.0, 0.4)
SHIFT = (0.3, 0.7)
UNRELATED = (
    "astronaut.png",
    "brick.png",
    "camera.png",
    "cell.png",
    "chelsea.png",
    "clock_motion.png",
    "coffee.png",
    "grass.png",
    "gravel.png",
    "hubble_deep_field.jpg",
    "ihc.png",
    "moon.png",
    "motorcycle_left.png",
    "motorcycle_right.png",
    "page.png",
    "retina.jpg",
    "rocket.jpg",
    "text.png",
)


def _skimage_data() -> Path | None:
    """scikit-image's sample-image folder, found without importing scikit-image."""
    spec = importlib.util.find_spec("skimage")
    for location in (spec.submodule_search_locations or []) if spec else []:
        if (Path(location) / "data" / "coins.png").is_file():
            return Path(location) / "data"
    return None


def _degrade(
    image: NDArray[Any], shift: tuple[float, float], sigma: float, gain: float
) -> NDArray[np.uint8]:
    moved = cv2.warpAffine(
        image.astype(np.float32),
        np.array([[1, 0, shift[0]], [0, 1, shift[1]]], np.float32),
        (image.shape[1], image.shape[0]),
        flags=cv2.INTER_LANCZOS4,
        borderMode=cv2.BORDER_REFLECT,
    )
    if sigma > 0:
        moved = cv2.GaussianBlur(moved, (0, 0), sigma)
    return np.asarray(np.clip(np.rint(moved * gain), 0, 255), np.uint8)


def _discs(seed: int, size: tuple[int, int]) -> tuple[NDArray[np.float64], list[Any]]:
    """Sharp anti-aliased bright discs (8x supersampled) on a gradient: image and truth."""
    rng = np.random.default_rng(seed)
    w, h = size
    canvas = 50.0 + np.linspace(-10, 10, w)[None, :] + np.zeros((h, 1))
    discs: list[tuple[float, float, float]] = []
    while len(discs) < 4:
        r = float(rng.uniform(20, 45))
        u, v = float(rng.uniform(r + 15, w - r - 15)), float(rng.uniform(r + 15, h - r - 15))
        if all(math.hypot(u - a, v - b) > r + c + 20 for a, b, c in discs):
            discs.append((u, v, r))
    s = 8
    ys, xs = np.mgrid[0 : h * s, 0 : w * s].astype(np.float32)
    xs, ys = (xs + 0.5) / s - 0.5, (ys + 0.5) / s - 0.5
    for u, v, r in discs:
        inside = ((xs - u) ** 2 + (ys - v) ** 2 <= r * r).astype(np.float32)
        cover = cv2.resize(inside, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)
        canvas += cover * (200.0 - canvas)
    return canvas, discs


def _nearest(found: list[Any], u: float, v: float) -> float:
    return min((math.hypot(f.u - u, f.v - v) for f in found), default=math.inf)


def run(cfg: RunConfig, env: Env) -> Section:
    from vision_server.analysis.locate import locate_circles

    section = Section(NAME, TITLE)
    sigmas = (0.0, 4.0) if cfg.quick else SIGMAS
    seeds = 1 if cfg.quick else 5
    size = (240, 180) if cfg.quick else (480, 360)

    rendered = Table(
        ["blur sigma px", "contrast", "found", "centre error median px", "max px", "ms per image"],
        caption=f"Rendered discs ({seeds} images of 4, {size[0]}x{size[1]}, noise 1.5 grey, "
        "exact answer):",
    )
    worst_rendered = 0.0
    missed_rendered = 0
    curves: dict[str, list[float]] = {}
    for gain in GAINS:
        for sigma in sigmas:
            errors: list[float] = []
            found_n = total = 0
            times: list[float] = []
            for seed in range(seeds):
                canvas, discs = _discs(seed, size)
                if sigma > 0:
                    canvas = np.asarray(cv2.GaussianBlur(canvas, (0, 0), sigma), np.float64)
                noisy = canvas * gain + np.random.default_rng(seed + 99).normal(
                    0, 1.5, canvas.shape
                )
                image = np.asarray(np.clip(np.rint(noisy), 0, 255), np.uint8)
                t0 = time.perf_counter()
                found = locate_circles(image, radius_range=(15, 50), max_count=10)
                times.append((time.perf_counter() - t0) * 1e3)
                for u, v, _ in discs:
                    e = _nearest(found, u, v)
                    total += 1
                    if e < 3.0:
                        found_n += 1
                        errors.append(e)
            missed_rendered += total - found_n
            worst = max(errors) if errors else math.nan
            worst_rendered = max(worst_rendered, worst if errors else math.inf)
            rendered.add(
                fmt(sigma, 1),
                f"{gain * 100:.0f} %",
                f"{found_n}/{total}",
                fmt(float(np.median(errors)) if errors else math.nan),
                fmt(worst),
                fmt(float(np.median(times)), 1),
            )
            section.value(f"rendered_s{sigma:g}_g{gain:g}_max_px", worst)
    section.tables.append(rendered)
    section.goals.append(
        Goal(
            "rendered discs, blur sigma 0..4 px at full and 40 % contrast: all found, centre "
            "error <= 0.1 px",
            f"{missed_rendered} missed, worst centre error {worst_rendered:.3f} px",
            missed_rendered == 0 and worst_rendered <= 0.1,
        )
    )

    data = _skimage_data()
    if data is None:
        section.skipped.append(
            "coins and unrelated photographs: scikit-image not installed (its wheel ships them)"
        )
    else:
        read = cv2.imread(str(data / "coins.png"), cv2.IMREAD_GRAYSCALE)
        if read is None:
            raise RuntimeError(f"cannot read {data / 'coins.png'}")
        coins = np.asarray(read, np.uint8)
        options: dict[str, Any] = {"radius_range": (15, 40), "max_count": 40, "min_score": 0.2}
        sharp = locate_circles(coins, **options)
        table = Table(
            [
                "blur sigma px",
                "contrast",
                "coins found",
                "centre vs sharp median px",
                "p95 px",
                "max px",
                "ms",
            ],
            caption=f"scikit-image's coins (24 coins, {coins.shape[1]}x{coins.shape[0]}), moved "
            f"by {SHIFT} px, min_score 0.2 (worn coins are not round); the sharp image finds "
            f"{len(sharp)}:",
        )
        coin_worst = 0.0
        coin_missed = 0
        for gain in GAINS:
            curve = []
            for sigma in sigmas:
                image = _degrade(coins, SHIFT, sigma, gain)
                t0 = time.perf_counter()
                found = locate_circles(image, **options)
                ms = (time.perf_counter() - t0) * 1e3
                errors = [_nearest(found, f.u + SHIFT[0], f.v + SHIFT[1]) for f in sharp]
                hit = [e for e in errors if e < 3.0]
                coin_missed += 24 - len(hit)
                coin_worst = max(coin_worst, max(hit) if hit else math.inf)
                curve.append(float(np.median(hit)) if hit else math.nan)
                table.add(
                    fmt(sigma, 1),
                    f"{gain * 100:.0f} %",
                    f"{len(hit)}/24",
                    fmt(float(np.median(hit)) if hit else math.nan),
                    fmt(float(np.percentile(hit, 95)) if hit else math.nan),
                    fmt(max(hit) if hit else math.nan),
                    fmt(ms, 1),
                )
                section.value(f"coins_s{sigma:g}_g{gain:g}_found", len(hit))
                section.value(
                    f"coins_s{sigma:g}_g{gain:g}_median_px",
                    float(np.median(hit)) if hit else math.nan,
                )
            curves[f"coins, {gain * 100:.0f} %"] = curve
        section.tables.append(table)
        section.goals.append(
            Goal(
                "coins photograph, blur sigma 0..4 px at full and 40 % contrast: every coin "
                "found, centre within 0.1 px of the sharp image's answer",
                f"{coin_missed} coin-images missed, worst centre error {coin_worst:.3f} px",
                coin_missed == 0 and coin_worst <= 0.1,
            )
        )
        reports = 0
        images = 0
        names = UNRELATED[:3] if cfg.quick else UNRELATED
        for name in names:
            photo = cv2.imread(str(data / name), cv2.IMREAD_GRAYSCALE)
            if photo is None:
                continue
            for sigma in sigmas:
                for gain in GAINS:
                    images += 1
                    found = locate_circles(
                        _degrade(photo, (0.0, 0.0), sigma, gain),
                        radius_range=(15, 40),
                        max_count=40,
                    )
                    reports += len(found)
        section.value("unrelated_images", images)
        section.value("unrelated_reports", reports)
        section.goals.append(
            Goal(
                "no part reported on scikit-image's unrelated photographs (every blur, contrast)",
                f"{reports} reported in {images} images",
                reports == 0,
            )
        )
        section.notes.append(
            f"Unrelated photographs ({len(names)} of scikit-image's, each at every blur and "
            f"contrast above: {images} images, default min_score 0.6, radii 15..40 px): "
            f"{reports} circles reported."
        )
        section.notes.append(
            "The issue's goal, centre within 0.1 px of the sharp answer at sigma 0..4, is met on "
            "rendered discs but not on the coins: they are worn and struck off-round (their "
            "outlines stray 1..2 px from any circle) and their rim relief and the light from one "
            "side are read into a blurred edge differently at each blur, so the fitted circle "
            "moves by a few tenths of a pixel (see the table)."
        )
    section.intro = (
        "locate_circles with its defaults (edge sigma measured per candidate). A part counts as "
        "found within 3 px of its answer."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for label, curve in curves.items():
            ax.plot(sigmas, curve, marker="o", label=label)
        ax.set_xlabel("blur sigma [px]")
        ax.set_ylabel("median centre error [px]")
        ax.grid(True, alpha=0.3)
        if curves:
            ax.legend(fontsize=8)
        return [save(fig, directory / "locate_blur.png")]

    section.plot = plot
    return section
