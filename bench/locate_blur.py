"""9. Circle locate through real optics: parts found and centre error against defocus blur
(Gaussian sigma 0..4 px) at full and 40 % contrast, on rendered discs (exact answer) and on
scikit-image's coins photograph (the sharp image's answer, the image moved by a known sub-pixel
amount), false reports on scikit-image's unrelated photographs, and the compute time of
:func:`vision_server.analysis.locate.locate_circles` per image; each with both ways of reading
the centre (``centre``: ``edge``, the default, and ``moments``)."""

from __future__ import annotations

import importlib.util
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from vision_server.analysis.locate import CENTRES, Centre

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
    # Bilinear: its kernel's centroid is exactly the shift asked for. OpenCV's Lanczos4 tables
    # (1/32 px steps) move the image by (0.325, 0.675) px for (0.3, 0.7): an error of 0.036 px
    # in every coin's answer, both methods', that was the bench's, not the locate's.
    moved = cv2.warpAffine(
        image.astype(np.float32),
        np.array([[1, 0, shift[0]], [0, 1, shift[1]]], np.float32),
        (image.shape[1], image.shape[0]),
        flags=cv2.INTER_LINEAR,
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


def _rendered_errors(
    centre: Centre, gain: float, sigma: float, seeds: int, size: tuple[int, int]
) -> tuple[list[float], int, list[float]]:
    """Rendered discs at one blur and contrast: centre errors (px) of the discs found, how
    many were missed, and the ms per image."""
    from vision_server.analysis import locate_circles

    errors: list[float] = []
    missed = 0
    times: list[float] = []
    for seed in range(seeds):
        canvas, discs = _discs(seed, size)
        if sigma > 0:
            canvas = np.asarray(cv2.GaussianBlur(canvas, (0, 0), sigma), np.float64)
        noisy = canvas * gain + np.random.default_rng(seed + 99).normal(0, 1.5, canvas.shape)
        image = np.asarray(np.clip(np.rint(noisy), 0, 255), np.uint8)
        t0 = time.perf_counter()
        found = locate_circles(image, radius_range=(15, 50), max_count=10, centre=centre)
        times.append((time.perf_counter() - t0) * 1e3)
        for u, v, _ in discs:
            e = _nearest(found, u, v)
            if e < 3.0:
                errors.append(e)
            else:
                missed += 1
    return errors, missed, times


def _key(centre: str) -> str:
    """Value-name infix: none for the default edge centre (names as before), else the method."""
    return "" if centre == "edge" else f"_{centre}"


def run(cfg: RunConfig, env: Env) -> Section:
    from vision_server.analysis import locate_circles

    section = Section(NAME, TITLE)
    sigmas = (0.0, 4.0) if cfg.quick else SIGMAS
    seeds = 1 if cfg.quick else 5
    size = (240, 180) if cfg.quick else (480, 360)

    rendered = Table(
        [
            "centre",
            "blur sigma px",
            "contrast",
            "found",
            "centre error median px",
            "max px",
            "ms per image",
        ],
        caption=f"Rendered discs ({seeds} images of 4, {size[0]}x{size[1]}, noise 1.5 grey, "
        "exact answer):",
    )
    worst_rendered = 0.0
    missed_rendered = 0
    worst_moments = 0.0
    missed_moments = 0
    curves: dict[str, list[float]] = {}
    for centre in CENTRES:
        for gain in GAINS:
            for sigma in sigmas:
                errors, missed, times = _rendered_errors(centre, gain, sigma, seeds, size)
                total = len(errors) + missed
                worst = max(errors) if errors else math.nan
                if centre == "edge":
                    missed_rendered += missed
                    worst_rendered = max(worst_rendered, worst if errors else math.inf)
                else:
                    missed_moments += missed
                    worst_moments = max(worst_moments, worst if errors else math.inf)
                rendered.add(
                    centre,
                    fmt(sigma, 1),
                    f"{gain * 100:.0f} %",
                    f"{len(errors)}/{total}",
                    fmt(float(np.median(errors)) if errors else math.nan),
                    fmt(worst),
                    fmt(float(np.median(times)), 1),
                )
                section.value(f"rendered{_key(centre)}_s{sigma:g}_g{gain:g}_max_px", worst)
    section.tables.append(rendered)
    section.goals.append(
        Goal(
            "rendered discs, blur sigma 0..4 px at full and 40 % contrast: all found, centre "
            "error <= 0.1 px",
            f"{missed_rendered} missed, worst centre error {worst_rendered:.3f} px",
            missed_rendered == 0 and worst_rendered <= 0.1,
        )
    )
    section.value("rendered_moments_worst_px", worst_moments)
    section.notes.append(
        f"centre: moments on the rendered discs (flat, evenly lit: the intensity centroid is "
        f"the outline's centre): {missed_moments} missed, worst centre error "
        f"{worst_moments:.3f} px against the true centre."
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
        table = Table(
            [
                "centre",
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
            f"{len(locate_circles(coins, **options))} (edge centres):",
        )
        coin_worst = dict.fromkeys(CENTRES, 0.0)
        coin_missed = dict.fromkeys(CENTRES, 0)
        inner_worst = dict.fromkeys(CENTRES, 0.0)  # coins whose outline is 5 px from the border
        height, width = coins.shape
        for centre in CENTRES:
            sharp = locate_circles(coins, centre=centre, **options)
            inner = [
                min(f.u, f.v, width - 1 - f.u, height - 1 - f.v) - (f.radius or 0.0) >= 5.0
                for f in sharp
            ]
            for gain in GAINS:
                curve = []
                for sigma in sigmas:
                    image = _degrade(coins, SHIFT, sigma, gain)
                    t0 = time.perf_counter()
                    found = locate_circles(image, centre=centre, **options)
                    ms = (time.perf_counter() - t0) * 1e3
                    errors = [_nearest(found, f.u + SHIFT[0], f.v + SHIFT[1]) for f in sharp]
                    hit = [e for e in errors if e < 3.0]
                    inner_hit = [e for e, keep in zip(errors, inner, strict=True) if keep]
                    inner_worst[centre] = max([inner_worst[centre], *inner_hit])
                    coin_missed[centre] += 24 - len(hit)
                    coin_worst[centre] = max(coin_worst[centre], max(hit) if hit else math.inf)
                    curve.append(float(np.median(hit)) if hit else math.nan)
                    table.add(
                        centre,
                        fmt(sigma, 1),
                        f"{gain * 100:.0f} %",
                        f"{len(hit)}/24",
                        fmt(float(np.median(hit)) if hit else math.nan),
                        fmt(float(np.percentile(hit, 95)) if hit else math.nan),
                        fmt(max(hit) if hit else math.nan),
                        fmt(ms, 1),
                    )
                    key = f"coins{_key(centre)}_s{sigma:g}_g{gain:g}"
                    section.value(f"{key}_found", len(hit))
                    section.value(f"{key}_median_px", float(np.median(hit)) if hit else math.nan)
                curves[f"coins, {centre}, {gain * 100:.0f} %"] = curve
        section.tables.append(table)
        section.value("coins_moments_inner_worst_px", inner_worst["moments"])
        best = min(CENTRES, key=lambda c: (coin_missed[c], coin_worst[c]))
        section.goals.append(
            Goal(
                "coins photograph, blur sigma 0..4 px at full and 40 % contrast: every coin "
                "found, centre within 0.1 px of the same method's sharp answer",
                "; ".join(
                    f"{c}: {coin_missed[c]} coin-images missed, worst centre error "
                    f"{coin_worst[c]:.3f} px"
                    for c in CENTRES
                ),
                coin_missed[best] == 0 and coin_worst[best] <= 0.1,
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
            "rendered discs but not on the coins (up to 1.7 px at sigma 4). Not because they "
            "are off-round (the last table: an off-round outline alone moves the centre by "
            "under 0.02 px) but because their rim, lit from one side, and their relief near the "
            "rim are read into a blurred edge, more at each blur (see the note below)."
        )
        section.notes.append(
            "centre: moments (the centre of each part's light at a common blur of 4.5 px, "
            "vision_server/analysis/circle_moments.py) is consistent where the edge is not: "
            f"worst {coin_worst['moments']:.3f} px from its sharp answer on the coins against "
            f"{coin_worst['edge']:.3f} px for edge; {inner_worst['moments']:.3f} px (edge: "
            f"{inner_worst['edge']:.3f}) over the {sum(inner)} coins whose outline is 5 px or "
            "more from the image's border. What moved it, found one at a time on the "
            "sharp image moved by the sub-pixel shift alone (sigma 0): (1) this bench's shift "
            "itself (OpenCV's Lanczos4 moves the light by (0.325, 0.675) px for (0.3, 0.7); "
            "now bilinear, exact: every coin's error fell by ~0.025 px); (2) hard window, "
            "neighbour and border masks, which gain or lose whole columns of light as the "
            "image moves (now smooth 5 px ramps that move with the centre); (3) the blur "
            "measured on the input, floored at 1 px when sharp and 0.1..0.2 px low when "
            "blurred, which left sharp and blurred images at different scales around a coin "
            "8 px from its neighbour (now measured again at the common scale and corrected); "
            "(4) a coin 10 px from its neighbour rejected at sigma 4, full contrast (its "
            "edge reading's levels reached the neighbour; now read again with less "
            "smoothing). What is left is one coin whose outline is 3.4 px from the image's "
            "right border (~0.15 px at every blur, sharp included): at the common scale its "
            "light mirrored at the border (both this bench's blur and the method's mirror "
            "there) is a like neighbour 7 px away that moves the other way when the image "
            "moves; no rule for the unseen scene beyond the border made it consistent "
            "(filling it with the background, or cutting the window 3..9 px inside it, "
            "traded it for errors on other coins near the border). It reads the centre of "
            "the light, not of the outline: the last table's lit rim and relief read ~0.6 px "
            "off the outline's centre at every blur, so edge stays the default."
        )
    _mechanisms(section, sigmas)
    section.intro = (
        "locate_circles with its defaults (edge sigma measured per candidate), with centre: "
        "edge (the default) and centre: moments. A part counts as found within 3 px of its "
        "answer."
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


MECHANISMS = (
    ("round", "a round disc"),
    ("off_round", "off-round outline (radius +-1.5 px, 2nd and 3rd harmonics)"),
    ("lit_rim", "round, a 2.5 px rim band up to 60 grey brighter on one side (side light)"),
    ("relief", "round, a dark engraving 4..7 px inside the rim on one side"),
    ("neighbour", "round, a second disc 9 px away"),
)


def _mechanism_disc(kind: str, centre: tuple[float, float], radius: float) -> NDArray[np.float64]:
    """160x160 px, 8x supersampled: a bright disc (150) on 40 with one coin-like feature."""
    s, size = 8, 160
    ys, xs = np.mgrid[0 : size * s, 0 : size * s].astype(np.float32)
    xs, ys = (xs + 0.5) / s - 0.5, (ys + 0.5) / s - 0.5
    theta = np.arctan2(ys - centre[1], xs - centre[0])
    rho = np.hypot(xs - centre[0], ys - centre[1])
    outline = radius + np.zeros_like(theta)
    if kind == "off_round":  # no first harmonic: the outline's centre stays where it was
        outline = outline + 1.5 * np.cos(2 * theta) + 0.8 * np.cos(3 * theta + 1.0)
    fine = np.full(rho.shape, 40.0, np.float32)
    inside = rho <= outline
    fine[inside] = 150.0
    if kind == "lit_rim":
        band = inside & (rho > outline - 2.5)
        fine[band] = 150.0 + 60.0 * (0.5 - 0.5 * np.cos(theta[band]))
    elif kind == "relief":
        fine[(rho < outline - 4) & (rho > outline - 7) & (np.cos(theta) > 0.3)] = 90.0
    elif kind == "neighbour":
        fine[np.hypot(xs - (centre[0] + radius + 29.0), ys - centre[1]) <= 20.0] = 150.0
    return np.asarray(cv2.resize(fine, (size, size), interpolation=cv2.INTER_AREA), np.float64)


def _mechanisms(section: Section, sigmas: tuple[float, ...]) -> None:
    """Why the coins' centres move with blur: one coin-like feature at a time on a rendered
    disc (40 % contrast, no noise), the centre found at each blur against the sharp one's."""
    from vision_server.analysis import locate_circles

    centre = (80.3, 79.6)
    table = Table(
        ["disc", "centre", "sharp vs true px", *[f"sigma {s:g}" for s in sigmas]],
        caption="Why a coin's centre moves with blur: centre found at each blur sigma (px) "
        "against the sharp image's, on a rendered disc (radius 22 px, 40 % contrast, no "
        "noise) with one coin-like feature at a time; and the sharp answer against the true "
        "centre of the outline:",
    )
    for key, label in MECHANISMS:
        base = _mechanism_disc(key, centre, 22.0)
        for method in CENTRES:
            row: list[str] = [label, method]
            sharp: tuple[float, float] | None = None
            for sigma in sigmas:
                blurred = cv2.GaussianBlur(base, (0, 0), sigma) if sigma > 0 else base
                image = np.asarray(np.clip(np.rint(blurred * 0.4), 0, 255), np.uint8)
                found = locate_circles(
                    image, radius_range=(15, 40), max_count=5, min_score=0.2, centre=method
                )
                near = [f for f in found if math.hypot(f.u - centre[0], f.v - centre[1]) < 3.0]
                if sharp is None:
                    if not near:
                        row.append("missed")
                        row.extend("" for _ in sigmas)
                        break
                    sharp = (near[0].u, near[0].v)
                    off = math.hypot(sharp[0] - centre[0], sharp[1] - centre[1])
                    row.append(fmt(off))
                    section.value(f"mechanism_{key}{_key(method)}_true_px", off)
                if not near:
                    row.append("missed")
                    continue
                moved = math.hypot(near[0].u - sharp[0], near[0].v - sharp[1])
                row.append(fmt(moved))
                section.value(f"mechanism_{key}{_key(method)}_s{sigma:g}_px", moved)
            table.add(*row)
    section.tables.append(table)
    section.notes.append(
        "An off-round outline alone does not move the centre with blur (the 50 % crossing of a "
        "smooth outline stays put), nor does a neighbour 9 px away much; grey-level structure "
        "within a few sigma inside the edge that differs around the part does: a rim lit from "
        "one side or relief near the rim on one side is mixed into the blurred edge, which "
        "moves outwards where the inside is brighter, by up to (extra area under the profile) "
        "/ (edge step): ~1.4 px for the lit rim above at full blur, so the centre moves ~0.6 px "
        "towards the light. The sharp image lets the reading stop at the true step; the blurred "
        "one no longer holds the difference between rim and step (at sigma 4 px the 2.5 px rim "
        "is gone into the edge), so no local edge reading can agree with the sharp answer "
        "there. Only one defined at a fixed coarse scale (the same for sharp and blurred "
        "images) could, at the price of the sharp image's accuracy against the true outline."
    )
