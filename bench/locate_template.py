"""10. Template locate through scale change and occlusion: centre, angle and scale error on
rendered textured parts of exactly known pose (simulation.textured_part), with the robust
alignment and with the correlation peak alone, and the compute time of every locate tool on a
1024x768 image beside a 3x3 box blur (cv2.blur) in the same run."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from simulation.textured_part import BACKGROUND, TexturedPart, random_part

from .common import Goal, RunConfig, Section, Stats, Table, fmt, ratio, time_calls
from .env import Env
from .plots import pyplot, save

NAME = "locate_template"
TITLE = "10. Template locate through scale change and occlusion; locate tools' compute time"

SEARCH: dict[str, Any] = {
    "angle_range": (-0.3, 0.3),
    "angle_step": 0.05,
    "scale_range": (0.88, 1.12),
    "scale_step": 0.03,
    "min_score": 0.4,
}
CONDITIONS: tuple[tuple[str, float | None], ...] = (
    ("scaled +-10 %, turned", None),
    ("+ a quarter hidden, dark (25)", 25.0),
    ("+ a quarter hidden, mid grey (120)", BACKGROUND),
    ("+ a quarter hidden, bright (230)", 230.0),
)


def _trial(
    part: TexturedPart, rng: np.random.Generator, seed: int, grey: float | None
) -> tuple[Any, tuple[float, float, float, float]]:
    u, v = rng.uniform(130, 190, 2)
    angle, scale = float(rng.uniform(-0.25, 0.25)), float(rng.uniform(0.9, 1.1))
    # A quarter of the template's disc: right of half its radius (0.2 of the disc's area).
    occluders = [] if grey is None else [(u + 16.0 * scale, v - 80.0, u + 100.0, v + 80.0, grey)]
    image = part.scene(
        [(float(u), float(v), angle, scale)], size=(320, 320), seed=seed, occluders=occluders
    )
    return image, (float(u), float(v), angle, scale)


def _accuracy(section: Section, cfg: RunConfig) -> dict[str, tuple[float, float]]:
    from vision_server.analysis import locate_template

    seeds = cfg.n(20, 1)
    part = random_part(7)
    template = part.template()
    table = Table(
        [
            "condition",
            "refinement",
            "found",
            "centre error median px",
            "max px",
            "angle max rad",
            "scale max",
            "score median",
        ],
        caption=f"Rendered textured parts ({seeds} per row, 320x320, template 65x65 px, noise "
        "2.5 grey; the search: angles ±0.3 rad in 0.05, scales 0.88..1.12 in 0.03, "
        "min_score 0.4). A quarter hidden: an occluder over the part's side beyond half the "
        "template's radius.",
    )
    worst: dict[str, tuple[float, float]] = {}
    for label, grey in CONDITIONS:
        for align in (True, False):
            rng = np.random.default_rng(2024)
            errors: list[float] = []
            angles: list[float] = []
            scales: list[float] = []
            scores: list[float] = []
            for seed in range(seeds):
                image, (u, v, angle, scale) = _trial(part, rng, seed, grey)
                found = locate_template(image, template, align=align, **SEARCH)
                if not found or math.hypot(found[0].u - u, found[0].v - v) > 5.0:
                    continue
                best = found[0]
                errors.append(math.hypot(best.u - u, best.v - v))
                angles.append(abs(best.angle - angle))
                scales.append(abs((best.scale or 1.0) - scale))
                scores.append(best.score)
            name = "aligned" if align else "correlation peak only"
            table.add(
                label,
                name,
                f"{len(errors)}/{seeds}",
                fmt(float(np.median(errors)) if errors else math.nan),
                fmt(max(errors) if errors else math.nan),
                fmt(max(angles) if angles else math.nan, 4),
                fmt(max(scales) if scales else math.nan, 4),
                fmt(float(np.median(scores)) if scores else math.nan),
            )
            key = f"{'aligned' if align else 'ncc'}_{'clear' if grey is None else int(grey)}"
            section.value(f"{key}_max_px", max(errors) if errors else math.nan)
            section.value(f"{key}_found", len(errors))
            worst[f"{label}|{name}"] = (
                max(errors) if errors else math.nan,
                len(errors) / seeds,
            )
    section.tables.append(table)
    aligned = [w for k, w in worst.items() if k.endswith("|aligned")]
    worst_px = max(w[0] for w in aligned)
    all_found = all(w[1] == 1.0 for w in aligned)
    section.goals.append(
        Goal(
            "template locate, scale ±10 % and a quarter hidden: every part found, centre "
            "within 0.1 px",
            f"{'all found' if all_found else 'some missed'}, worst centre error {worst_px:.3f} px",
            all_found and worst_px <= 0.1,
        )
    )
    return worst


def _timing(section: Section, cfg: RunConfig) -> None:
    from vision_server.analysis import locate_blobs, locate_circles, locate_template

    part = random_part(7)
    template = part.template()
    width, height = (1024, 768) if not cfg.quick else (400, 300)
    poses = [(100.5, 90.25, 0.1, 1.0), (width - 120.25, height - 100.5, -0.15, 1.05)]
    image = part.scene(poses, size=(width, height), seed=1)
    discs = image.copy()
    for u, v, r in ((width // 4, height * 3 // 4, 40), (width * 3 // 4, height // 4, 32)):
        cv2.circle(discs, (u, v), r, 220, -1, cv2.LINE_AA)
    repeat = cfg.n(15, 1)
    tools: list[tuple[str, str, Callable[[], object]]] = [
        ("blur3", "3x3 box blur (cv2.blur), the reference", lambda: cv2.blur(image, (3, 3))),
        (
            "template",
            "locate template, no search",
            lambda: locate_template(image, template, max_count=2),
        ),
        (
            "template_angles",
            "locate template, angles ±0.3 rad in 0.05",
            lambda: locate_template(
                image, template, max_count=2, angle_range=(-0.3, 0.3), angle_step=0.05
            ),
        ),
        (
            "template_angles_scales",
            "locate template, angles ±0.3 rad in 0.05 x scales 0.88..1.12 in 0.03",
            lambda: locate_template(image, template, max_count=2, **SEARCH),
        ),
        (
            "template_angles_scales_ncc_only",
            "locate template, angles ±0.3 x scales, correlation peak only",
            lambda: locate_template(image, template, max_count=2, align=False, **SEARCH),
        ),
        (
            "circle",
            "locate circle, radii 20..50 px",
            lambda: locate_circles(discs, radius_range=(20, 50), max_count=10),
        ),
        ("blob", "locate blob, Otsu", lambda: locate_blobs(discs, min_area=200.0)),
    ]
    table = Table(
        ["tool", "ms p50", "ms p95", "x the 3x3 blur"],
        caption=f"Compute per {width}x{height} gray image, one thread, {repeat} calls after "
        "one warm-up (the same run, the same machine):",
    )
    reference = math.nan
    for key, label, call in tools:
        stats = Stats.of(time_calls(call, repeat=repeat, warmup=1))
        if math.isnan(reference):
            reference = stats.p50
        table.add(label, fmt(stats.p50, 2), fmt(stats.p95, 2), ratio(stats.p50, reference))
        section.value(f"ms_{key}", stats.p50)
    section.tables.append(table)


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    worst = _accuracy(section, cfg)
    _timing(section, cfg)
    section.intro = (
        "locate_template: normalised cross-correlation over rotations and scales (a halved "
        "image first), then each peak's pose refined by robust alignment (position, angle, "
        "scale, gain and offset; occluded areas get no weight). The 'correlation peak only' "
        "rows are the same search without that refinement: an occluder pulls the peak "
        "towards the poses that put less of the template over it."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(6.5, 3.5))
        labels = [label for label, _ in CONDITIONS]
        x = np.arange(len(labels))
        for offset, name in ((-0.2, "aligned"), (0.2, "correlation peak only")):
            ax.bar(
                x + offset,
                [worst[f"{label}|{name}"][0] for label in labels],
                width=0.4,
                label=name,
            )
        ax.set_xticks(x, [label.replace("+ a quarter hidden, ", "hidden ") for label in labels])
        ax.set_ylabel("worst centre error [px]")
        ax.set_yscale("log")
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
        return [save(fig, directory / "locate_template.png")]

    section.plot = plot
    return section
