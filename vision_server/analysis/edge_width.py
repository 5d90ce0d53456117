"""How blurred is a circle's edge: the edge width (Gaussian sigma, px) seen along radial rays.

Circle refinement reads an edge's inner and outer grey levels a fixed distance from its steepest
step; a defocused or moving part spreads that step over several pixels, so the distances must
grow with the blur or the levels are read on the slope and every ray is rejected. This module
measures the blur once per candidate so that :mod:`.locate` can scale its windows.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["SHARP_SIGMA", "edge_sigma"]

FloatArray = NDArray[np.float64]

SHARP_SIGMA = 1.0
"""Sigma (px) up to which an edge counts as sharp. An in-focus edge sampled here (pixel
footprint, bilinear interpolation, a little optical blur) measures 0.6..1 px, which the original
windows (levels read 1.5..2 px from the step) already fit."""

_FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
_STEP = 0.25  # px between samples along a ray


def edge_sigma(
    image: FloatArray,
    centre: tuple[float, float],
    radius: float,
    *,
    polarity: Literal["bright", "dark"],
    rays: int = 64,
    reach: float | None = None,
    interpolate: bool = False,
) -> float | None:
    """Median edge sigma (px) of a roughly circular edge near ``radius`` around ``centre``.

    On each ray (samples ``_STEP`` px apart, bilinear) the derivative of the intensity going
    outwards is taken; around its strongest fall (bright disc) or rise (dark disc) the full
    width at half maximum of that peak gives the ray's sigma (FWHM / 2.355, a Gaussian-blurred
    step's derivative being a Gaussian). The median over rays resists texture and neighbours.

    Parameters
    ----------
    image : ndarray
        Gray image as float64 ``(H, W)``.
    centre : (float, float)
        Guessed centre ``(u, v)``, px, in ``image``'s pixels.
    radius : float
        Guessed radius, px.
    polarity : {'bright', 'dark'}
    rays : int
        Rays cast.
    reach : float, optional
        Half-width (px) of the radial window searched, default ``max(8, 0.35 * radius)``.
    interpolate : bool
        Place each half-maximum crossing by linear interpolation between samples, so that the
        answer varies continuously with the blur (default: counted in whole samples, which
        steps by 0.1 px of sigma) and is not raised to :data:`SHARP_SIGMA`.

    Returns
    -------
    float or None
        Sigma in px (at least :data:`SHARP_SIGMA`), or None when fewer than a quarter of the
        rays show a peak inside the window (no edge there).
    """
    half = max(8.0, 0.35 * radius) if reach is None else reach
    lo = max(radius - half, 0.5)
    radii = np.arange(lo, radius + half + _STEP / 2, _STEP)
    theta = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)
    map_x = (centre[0] + np.cos(theta)[:, None] * radii[None, :]).astype(np.float32)
    map_y = (centre[1] + np.sin(theta)[:, None] * radii[None, :]).astype(np.float32)
    profiles = cv2.remap(
        image.astype(np.float32),
        map_x,
        map_y,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    ).astype(np.float64)
    if polarity == "bright":
        profiles = -profiles
    widths: list[float] = []
    for profile in profiles:
        if np.isnan(profile).any():
            continue
        # Rise going outwards over 0.5 px (two samples either side), per px.
        slope = (profile[4:] - profile[:-4]) / (4 * _STEP)
        peak = int(np.argmax(slope))
        top = float(slope[peak])
        if top <= 0.0 or peak in (0, len(slope) - 1):
            continue
        above = slope >= 0.5 * top
        left = peak
        while left > 0 and above[left - 1]:
            left -= 1
        right = peak
        while right < len(slope) - 1 and above[right + 1]:
            right += 1
        if left == 0 or right == len(slope) - 1:
            continue  # the peak runs off the window: not an edge we can measure
        if interpolate:
            half_top = 0.5 * top
            first = left - 1 + (half_top - slope[left - 1]) / (slope[left] - slope[left - 1])
            last = right + (slope[right] - half_top) / (slope[right] - slope[right + 1])
            widths.append(float(last - first) * _STEP / _FWHM_PER_SIGMA)
        else:
            widths.append((right - left + 1) * _STEP / _FWHM_PER_SIGMA)
    if len(widths) < max(4, rays // 4):
        return None
    if interpolate:
        return float(np.median(widths))
    return max(float(np.median(widths)), SHARP_SIGMA)
