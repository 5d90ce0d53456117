"""Sub-pixel QR corners (qr.refine_corners): the fast line fit against a plain reference of the
documented algorithm, and the layouts used only by large codes."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from vision_server.analysis.qr import _line_fits, refine_corners

from .conftest import qr_modules, render_qr, square_corners

TEXT = "cellvision:station-1"
Line = tuple[float, float, float]


def _reference_fit(x: NDArray[np.float64], y: NDArray[np.float64], tol: float) -> Line:
    """One side, the way the fit was first written: orthogonal least squares on the kept
    points, the band halving from 12 tolerances to a floor of 1 over six rounds
    (-limit < d, and d < 3 limit from the second round), done from the 1.5 round on as soon as
    a round keeps the very points its line was fitted to."""
    keep = np.ones(x.size, bool)
    line: Line = (0.0, 0.0, 0.0)
    for it in range(6):
        px, py = x[keep], y[keep]
        cx, cy = px.mean(), py.mean()
        scatter = np.cov(np.stack([px - cx, py - cy]), bias=True)
        _, vectors = np.linalg.eigh(scatter)
        a, b = vectors[:, 0]  # the normal: the scatter's minor axis
        if b < 0:
            a, b = -a, -b
        line = (float(a), float(b), float(-(a * cx + b * cy)))
        dist = a * x + b * y + line[2]
        limit = max(tol, 12.0 * 0.5**it * tol)
        new_keep = dist > -limit
        if it > 0:
            new_keep &= dist < 3.0 * limit
        if it > 2 and (new_keep == keep).all():
            break
        keep = new_keep
    return line


def _side_points(rng: np.random.Generator, n: int) -> tuple[NDArray[np.float64], ...]:
    """Crossings along one side (x px, y px outward): the edge with noise, a third of them a
    module or more inside (light outermost modules), a few outward (glare), a few missing."""
    x = np.linspace(-90.0, 90.0, n)
    y = rng.normal(0.2, 0.5) + rng.normal(0.0, 0.01) * x + rng.normal(0.0, 0.12, n)
    inside = rng.random(n) < 0.33
    y[inside] -= rng.choice([1.0, 2.0, 3.0], inside.sum()) * rng.uniform(2.5, 5.0)
    outward = rng.random(n) < 0.04
    y[outward] += rng.uniform(0.5, 4.0, outward.sum())
    valid = rng.random(n) > 0.05
    return x, y, valid


def test_the_fast_line_fit_matches_the_reference_fit() -> None:
    """Fails when the band schedule, the convergence test or the per-side bookkeeping of the
    fit of all four sides at once departs from the plain per-side fit (e.g. with the schedule
    12, 3, 1.5, 1, which the photographs rejected)."""
    rng = np.random.default_rng(19)
    checked = 0
    for _ in range(40):
        sides = [_side_points(rng, 90) for _ in range(4)]
        x = np.stack([s[0] for s in sides])
        y = np.stack([s[1] for s in sides])
        valid = np.stack([s[2] for s in sides])
        tol = float(rng.uniform(0.35, 1.2))
        fast = _line_fits(x, y, valid, tol)
        assert fast is not None
        for k in range(4):
            ref = _reference_fit(x[k][valid[k]], y[k][valid[k]], tol)
            np.testing.assert_allclose(fast[k], ref, atol=1e-9)
            checked += 1
    assert checked == 160


def test_too_few_points_on_a_side_gives_no_lines() -> None:
    rng = np.random.default_rng(3)
    sides = [_side_points(rng, 40) for _ in range(4)]
    x, y, valid = (np.stack([side[i] for side in sides]) for i in range(3))
    valid[2] = False
    valid[2, :3] = True
    assert _line_fits(x, y, valid, 0.5) is None


def test_a_large_code_read_in_several_remap_rows_is_refined() -> None:
    """A 400 px code has more samples than remap's 32767 columns: the profiles are read as
    several rows."""
    truth = square_corners((320.0, 240.0), 400.0, 10.0)
    img = render_qr(TEXT, truth, blur_sigma=1.0, noise_sigma=2)
    rough = truth + np.random.default_rng(5).normal(0.0, 1.0, (4, 2))
    refined = refine_corners(img, rough, modules=qr_modules(TEXT).shape[0])
    assert np.abs(refined - truth).max() < 0.3 < np.abs(rough - truth).max()


def test_a_huge_code_with_more_samples_per_profile_than_cached_is_refined() -> None:
    """Modules of 170 px: more than 1024 samples across each side (the cached step indices)."""
    modules = qr_modules(TEXT)
    px, quiet = 170, 2
    n = modules.shape[0]
    size = (n + 2 * quiet) * px
    img = np.full((size, size), 220, np.uint8)
    dark = np.kron(modules, np.ones((px, px), np.uint8)) > 0
    img[quiet * px : (quiet + n) * px, quiet * px : (quiet + n) * px][dark] = 30
    lo, hi = quiet * px - 0.5, (quiet + n) * px - 0.5  # pixel centres: the boundary's position
    truth = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
    rough = truth + np.array([[3.0, -2.0], [-4.0, 2.5], [2.0, 3.0], [-2.5, -3.5]])
    refined = refine_corners(img, rough, modules=n)
    assert np.abs(refined - truth).max() < 0.1
