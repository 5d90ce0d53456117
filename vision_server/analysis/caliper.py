"""Calipers: sub-pixel edges along a band, the pairs of edges around a part and their widths.

Frames and units: image pixels ``(u, v)`` = (column, row), the centre of the top-left pixel
being ``(0.0, 0.0)`` (docs/conventions.md, as :mod:`.locate`). A :class:`Band` is a rectangle
of the *part frame*: the image's pixels unless a 2x3 ``image_from_part`` affine (a job's
fixture, ``[[c, -s, u0], [s, c, v0]]`` for a part at angle ``a`` whose origin is at
``(u0, v0)``) maps its points into the image. Its scan runs along ``angle_rad`` (from +u
towards +v: clockwise on the screen, as locate's angles); the profile is averaged across its
width. Edge positions come back in image pixels; offsets along the scan in image pixels too.

How an edge is found: the band is sampled 1 px apart (bilinear) and averaged across; the
profile is differentiated with a Gaussian derivative of ``smoothing`` px (normalised so that
a ramp of slope ``g`` grey levels per px reads ``g``); each local extremum of the derivative
of the requested sign whose magnitude reaches ``min_strength`` is an edge, placed to sub-pixel
precision by a Gaussian fit through the extremum and its two neighbours (exact for the
Gaussian-shaped derivative of a blurred step; a parabola where a neighbour has the other sign).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .errors import BadImageError, NotFoundError, RoiError

__all__ = [
    "Band",
    "Edge",
    "EdgePair",
    "Polarity",
    "Selection",
    "find_edges",
    "find_edges_in_bands",
    "find_pairs",
    "gray_float",
    "select_edges",
]

FloatArray = NDArray[np.float64]
Affine = NDArray[np.float64]
"""A 2x3 matrix taking part-frame points ``(x, y, 1)`` to image pixels ``(u, v)``."""

Polarity = Literal["dark_to_light", "light_to_dark", "any"]
Selection = Literal["first", "last", "strongest", "all"]
POLARITIES: tuple[str, ...] = ("dark_to_light", "light_to_dark", "any")
SELECTIONS: tuple[str, ...] = ("first", "last", "strongest", "all")

_KERNEL_REACH = 4.0  # the Gaussian derivative is cut at this many sigmas


@dataclass(frozen=True)
class Band:
    """A caliper's rectangle in the part frame (px): centre ``(u, v)``, ``length`` along the
    scan, ``width`` across it (the profile is the mean across), scan direction ``angle_rad``
    from +u towards +v. A width of 1 is a single line."""

    u: float
    v: float
    length: float
    width: float = 1.0
    angle_rad: float = 0.0

    def __post_init__(self) -> None:
        for key in ("u", "v", "angle_rad"):
            if not math.isfinite(getattr(self, key)):
                raise ValueError(f"band {key} must be finite, got {getattr(self, key)!r}")
        if not (math.isfinite(self.length) and self.length >= 3.0):
            raise ValueError(f"band length must be >= 3 px, got {self.length!r}")
        if not (math.isfinite(self.width) and self.width >= 1.0):
            raise ValueError(f"band width must be >= 1 px, got {self.width!r}")

    @property
    def direction(self) -> tuple[float, float]:
        """Unit scan direction in the part frame."""
        return math.cos(self.angle_rad), math.sin(self.angle_rad)

    def point(self, offset: float, across: float = 0.0) -> tuple[float, float]:
        """The part-frame point ``offset`` px along the scan from the band's start and
        ``across`` px towards the scan's left-hand normal (+90 degrees)."""
        c, s = self.direction
        t = offset - self.length / 2.0
        return self.u + t * c - across * s, self.v + t * s + across * c


@dataclass(frozen=True)
class Edge:
    """One edge: ``(u, v)`` in image pixels, ``offset`` along the scan from the band's start
    (image px), ``strength`` the profile's slope there in grey levels per px along the scan
    (positive: dark to light); ``spread`` the Gaussian sigma (image px) of the slope's peak
    (blur, pixel footprint and ``smoothing`` together; NaN where it cannot be fitted).
    """

    u: float
    v: float
    offset: float
    strength: float
    spread: float = math.nan

    @property
    def polarity(self) -> Polarity:
        return "dark_to_light" if self.strength > 0 else "light_to_dark"


@dataclass(frozen=True)
class EdgePair:
    """Two edges of one scan, ``first`` before ``second``: the two sides of a part or a gap."""

    first: Edge
    second: Edge

    @property
    def width_px(self) -> float:
        """Distance between the two edges in image pixels."""
        return math.hypot(self.second.u - self.first.u, self.second.v - self.first.v)

    @property
    def centre(self) -> tuple[float, float]:
        """Midpoint ``(u, v)`` of the two edges, image pixels."""
        return (self.first.u + self.second.u) / 2.0, (self.first.v + self.second.v) / 2.0


def gray_float(given: NDArray[np.generic]) -> NDArray[np.float32]:
    """``given`` (gray or BGR, uint8, uint16 or float) as a float32 gray image; a float32 gray
    image is returned as it is, so that a caller running many scans converts it once."""
    if not isinstance(given, np.ndarray) or given.size == 0:
        raise BadImageError("image must be a non-empty numpy array")
    image: NDArray[Any] = given
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(image, code)
    if image.ndim != 2:
        raise BadImageError(f"image must be gray (H, W) or BGR (H, W, 3), got shape {image.shape}")
    if image.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise BadImageError(f"image dtype {image.dtype} is not uint8, uint16 or float")
    return np.asarray(image, np.float32)


def _affine(image_from_part: Affine | None) -> Affine:
    if image_from_part is None:
        return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    matrix = np.asarray(image_from_part, np.float64)
    if matrix.shape != (2, 3) or not np.isfinite(matrix).all():
        raise ValueError(f"image_from_part must be a finite 2x3 matrix, got {matrix.tolist()}")
    if abs(float(np.linalg.det(matrix[:, :2]))) < 1e-9:
        raise ValueError("image_from_part is singular (it folds the part frame onto a line)")
    return matrix


def _profiles(
    gray: NDArray[np.float32], bands: Sequence[Band], matrix: Affine
) -> tuple[FloatArray, FloatArray, list[float]]:
    """The bands' profiles ``(len(bands), samples)`` (mean across, 1 part-px steps; the
    bands share length and width), the part-frame offsets of the samples, and each band's
    image px per part px along the scan. One remap for all of them."""
    length, band_width = bands[0].length, bands[0].width
    count = int(math.floor(length)) + 1
    offsets = np.arange(count, dtype=np.float64) + (length - (count - 1)) / 2.0
    lanes = max(1, int(round(band_width)))
    across = np.linspace(-(band_width - 1) / 2.0, (band_width - 1) / 2.0, lanes)
    t = offsets - length / 2.0
    c = np.array([math.cos(b.angle_rad) for b in bands])[:, None, None]
    s = np.array([math.sin(b.angle_rad) for b in bands])[:, None, None]
    bu = np.array([b.u for b in bands])[:, None, None]
    bv = np.array([b.v for b in bands])[:, None, None]
    x = bu + t[None, None, :] * c - across[None, :, None] * s
    y = bv + t[None, None, :] * s + across[None, :, None] * c
    u = matrix[0, 0] * x + matrix[0, 1] * y + matrix[0, 2]
    v = matrix[1, 0] * x + matrix[1, 1] * y + matrix[1, 2]
    height, width = gray.shape
    outside = (u.min(axis=(1, 2)) < 0) | (v.min(axis=(1, 2)) < 0)
    outside |= (u.max(axis=(1, 2)) > width - 1) | (v.max(axis=(1, 2)) > height - 1)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        band = bands[k]
        raise RoiError(
            f"band at ({band.u:.1f}, {band.v:.1f}) length {band.length:g} width {band.width:g} "
            f"angle {band.angle_rad:.3f} rad reaches outside the {width}x{height} image "
            f"(u {u[k].min():.1f}..{u[k].max():.1f}, v {v[k].min():.1f}..{v[k].max():.1f})"
        )
    samples = cv2.remap(
        gray,
        u.reshape(-1, count).astype(np.float32),
        v.reshape(-1, count).astype(np.float32),
        cv2.INTER_LINEAR,
    )
    profiles = np.asarray(samples, np.float64).reshape(len(bands), lanes, count).mean(axis=1)
    stretch = [
        math.hypot(matrix[0, 0] * b.direction[0] + matrix[0, 1] * b.direction[1],
                   matrix[1, 0] * b.direction[0] + matrix[1, 1] * b.direction[1])
        for b in bands
    ]  # fmt: skip
    return profiles, offsets, stretch


@lru_cache(maxsize=32)
def _kernel(smoothing: float) -> NDArray[np.float64]:
    """The Gaussian-derivative weights (1, 2 reach + 1), scaled so that a ramp of slope g
    reads g."""
    reach = max(1, int(math.ceil(_KERNEL_REACH * smoothing)))
    x = np.arange(-reach, reach + 1, dtype=np.float64)
    weights = x * np.exp(-0.5 * (x / smoothing) ** 2)
    weights /= float(np.sum(x * weights))
    return weights[None, :]


def _derivative(profiles: FloatArray, smoothing: float) -> FloatArray:
    """Gaussian-derivative slope of each profile (row; grey levels per sample), one per sample.

    The profiles are extended by repeating their end values, so that a short band (a search
    window of a few px) still has a slope everywhere; an edge the band cuts reads weaker
    near its ends, and no edge is reported at the end samples themselves."""
    kernel = _kernel(smoothing)
    reach = kernel.shape[1] // 2
    padded = np.pad(profiles, ((0, 0), (reach, reach)), mode="edge")
    slope = cv2.filter2D(padded, cv2.CV_64F, kernel, borderType=cv2.BORDER_REPLICATE)
    return np.asarray(slope[:, reach : reach + profiles.shape[1]], np.float64)


def _peak(left: float, centre: float, right: float) -> tuple[float, float]:
    """Sub-sample position of a peak through three samples (Gaussian fit, else parabola) and
    its Gaussian sigma in samples (NaN without the Gaussian fit)."""
    spread = math.nan
    if left > 0 and right > 0:
        la, lb, lc = math.log(left), math.log(centre), math.log(right)
        denom = la - 2.0 * lb + lc
        if denom < 0:
            spread = math.sqrt(-1.0 / denom)
    else:
        la, lc = left, right
        denom = left - 2.0 * centre + right
    if denom >= 0:  # flat top: no curvature to locate it by
        return 0.0, spread
    return max(-0.5, min(0.5, 0.5 * (la - lc) / denom)), spread


def find_edges(
    image: NDArray[np.generic],
    band: Band,
    *,
    polarity: Polarity = "any",
    min_strength: float = 5.0,
    smoothing: float = 1.0,
    select: Selection = "all",
    image_from_part: Affine | None = None,
) -> list[Edge]:
    """Sub-pixel edges across ``band``, ordered along the scan.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) ndarray
        Gray or BGR image.
    band : Band
        Where to look, in the part frame (the image's pixels without ``image_from_part``).
    polarity : {'dark_to_light', 'light_to_dark', 'any'}
        Which way the grey level must step along the scan.
    min_strength : float
        Smallest slope, grey levels per part px along the scan, of an edge.
    smoothing : float
        Sigma (px) of the Gaussian derivative: larger resists noise and texture.
    select : {'first', 'last', 'strongest', 'all'}
        Which edges to return (one, or every one).
    image_from_part : (2, 3) ndarray, optional
        The fixture: part frame to image pixels.

    Raises
    ------
    BadImageError, RoiError (the band leaves the image), ValueError (bad options).
    """
    return find_edges_in_bands(
        image,
        [band],
        polarity=polarity,
        min_strength=min_strength,
        smoothing=smoothing,
        select=select,
        image_from_part=image_from_part,
    )[0]


def find_edges_in_bands(
    image: NDArray[np.generic],
    bands: Sequence[Band],
    *,
    polarity: Polarity = "any",
    min_strength: float = 5.0,
    smoothing: float = 1.0,
    select: Selection = "all",
    image_from_part: Affine | None = None,
) -> list[list[Edge]]:
    """:func:`find_edges` on each of ``bands`` (of one length and width, e.g. the radial
    scans of a circle), sampled together: the edges of each, in order."""
    if polarity not in POLARITIES:
        raise ValueError(f"polarity must be one of {', '.join(POLARITIES)}, got {polarity!r}")
    if select not in SELECTIONS:
        raise ValueError(f"select must be one of {', '.join(SELECTIONS)}, got {select!r}")
    if not (math.isfinite(smoothing) and 0.3 <= smoothing <= 20.0):
        raise ValueError(f"smoothing must be a sigma in 0.3..20 px, got {smoothing!r}")
    if not (math.isfinite(min_strength) and min_strength > 0):
        raise ValueError(f"min_strength must be > 0 grey levels per px, got {min_strength!r}")
    if not bands:
        return []
    if any(b.length != bands[0].length or b.width != bands[0].width for b in bands):
        raise ValueError("bands scanned together must share their length and width")
    matrix = _affine(image_from_part)
    profiles, offsets, stretches = _profiles(gray_float(image), bands, matrix)
    slope = _derivative(profiles, smoothing)
    if polarity == "dark_to_light":
        signal = slope
    elif polarity == "light_to_dark":
        signal = -slope
    else:
        signal = np.abs(slope)
    middle = signal[:, 1:-1]
    peaks = (middle >= min_strength) & (middle > signal[:, :-2]) & (middle >= signal[:, 2:])
    found: list[list[Edge]] = [[] for _ in bands]
    for k, j in zip(*np.nonzero(peaks), strict=True):
        i = int(j) + 1
        row = signal[k]
        shift, spread = _peak(float(row[i - 1]), float(row[i]), float(row[i + 1]))
        at = float(offsets[i]) + shift  # samples are 1 part px apart
        band, stretch = bands[k], stretches[k]
        u, v = band.point(at)
        found[k].append(
            Edge(
                float(matrix[0, 0] * u + matrix[0, 1] * v + matrix[0, 2]),
                float(matrix[1, 0] * u + matrix[1, 1] * v + matrix[1, 2]),
                at * stretch,
                float(slope[k, i]) / stretch,
                spread * stretch,
            )
        )
    return [select_edges(edges, select) for edges in found]


def select_edges(edges: list[Edge], select: Selection) -> list[Edge]:
    """``edges`` (ordered along the scan) narrowed to the selection."""
    if not edges or select == "all":
        return edges
    if select == "first":
        return edges[:1]
    if select == "last":
        return edges[-1:]
    return [max(edges, key=lambda e: abs(e.strength))]


def find_pairs(
    image: NDArray[np.generic],
    band: Band,
    *,
    first: Polarity = "dark_to_light",
    second: Polarity = "light_to_dark",
    expected_width: float | None = None,
    width_tolerance: float | None = None,
    min_strength: float = 5.0,
    smoothing: float = 1.0,
    select: Selection = "strongest",
    image_from_part: Affine | None = None,
) -> list[EdgePair]:
    """Pairs of edges across ``band``: an edge of polarity ``first`` followed along the scan
    by one of polarity ``second`` (a bright part on a dark ground scanned across is
    dark_to_light then light_to_dark).

    Candidates are every such ordered pair; with ``expected_width`` (image px) those within
    ``width_tolerance`` px of it (all, without a tolerance), ranked by closeness to it, else
    by the weaker edge's strength. ``select``: the best ranked (``strongest``), the one that
    starts first or ends last along the scan, or ``all``: every ``first`` edge with the
    nearest ``second`` edge after it, in scan order, none overlapping (each part across the
    scan).

    Raises
    ------
    NotFoundError
        No pair of those polarities (within the tolerance).
    """
    if expected_width is not None and not (math.isfinite(expected_width) and expected_width > 0):
        raise ValueError(f"expected_width must be > 0 px, got {expected_width!r}")
    if width_tolerance is not None and not (
        math.isfinite(width_tolerance) and width_tolerance >= 0
    ):
        raise ValueError(f"width_tolerance must be >= 0 px, got {width_tolerance!r}")
    for key, value in (("first", first), ("second", second)):
        if value not in POLARITIES:
            raise ValueError(f"{key} must be one of {', '.join(POLARITIES)}, got {value!r}")
    edges = find_edges(
        image,
        band,
        polarity="any",
        min_strength=min_strength,
        smoothing=smoothing,
        select="all",
        image_from_part=image_from_part,
    )
    candidates = [
        EdgePair(a, b)
        for i, a in enumerate(edges)
        for b in edges[i + 1 :]
        if first in ("any", a.polarity) and second in ("any", b.polarity)
    ]
    if expected_width is not None and width_tolerance is not None:
        candidates = [p for p in candidates if abs(p.width_px - expected_width) <= width_tolerance]
    if not candidates:
        within = (
            f" within {width_tolerance:g} px of {expected_width:g} px"
            if expected_width is not None and width_tolerance is not None
            else ""
        )
        raise NotFoundError(
            f"no {first} edge followed by a {second} edge{within} across the band "
            f"({len(edges)} edges of strength >= {min_strength:g})"
        )

    def rank(pair: EdgePair) -> tuple[float, float]:
        weaker = min(abs(pair.first.strength), abs(pair.second.strength))
        miss = 0.0 if expected_width is None else abs(pair.width_px - expected_width)
        return miss, -weaker

    ranked = sorted(candidates, key=rank)
    if select == "strongest":
        return ranked[:1]
    if select == "first":
        return [min(ranked, key=lambda p: p.first.offset)]
    if select == "last":
        return [max(ranked, key=lambda p: p.second.offset)]
    # every part (or gap) across the scan: each first-polarity edge with the next
    # second-polarity edge after it, in scan order, none overlapping an earlier one
    kept: list[EdgePair] = []
    for pair in sorted(candidates, key=lambda p: (p.first.offset, p.second.offset)):
        if kept and pair.first.offset <= kept[-1].second.offset:
            continue
        if any(
            e is not pair.first
            and pair.first.offset < e.offset < pair.second.offset
            and second in ("any", e.polarity)
            for e in edges
        ):
            continue  # not the nearest closing edge
        kept.append(pair)
    return kept
