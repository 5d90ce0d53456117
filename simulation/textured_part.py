"""A flat textured part with an exactly known pose, for template-locate accuracy tests and the
bench: the texture is a sum of Gaussian spots, known at every real-valued point, so a part turned
and scaled by any amount is rendered without resampling error.

Poses are ``(u, v, angle, scale)``: the part's reference point (the template's centre) at
``(u, v)`` full-image pixels, turned by ``angle`` rad (+u towards +v) and scaled by ``scale``
(image size / template size); an object point ``p`` (template pixels from its centre) appears at
``(u, v) + scale * R(angle) p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["TexturedPart", "random_part"]

FloatArray = NDArray[np.float64]

BACKGROUND = 120.0
"""Grey level of the background and the texture's mean level."""


@dataclass(frozen=True)
class TexturedPart:
    """A part's texture: Gaussian spots ``(n, 4)`` = (x, y, sigma, amplitude), template px."""

    spots: FloatArray

    def texture(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Grey-level offset from :data:`BACKGROUND` at object points (template px)."""
        out = np.zeros_like(x)
        for sx, sy, sigma, amplitude in self.spots:
            out += amplitude * np.exp(-((x - sx) ** 2 + (y - sy) ** 2) / (2.0 * sigma * sigma))
        return out

    def template(self, half: int = 32) -> NDArray[np.uint8]:
        """The template: ``(2 half + 1)`` px square, its centre the object's origin."""
        y, x = np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64)
        return np.clip(np.rint(BACKGROUND + self.texture(x, y)), 0, 255).astype(np.uint8)

    def scene(
        self,
        poses: list[tuple[float, float, float, float]],
        *,
        size: tuple[int, int],
        noise: float = 2.5,
        seed: int = 0,
        occluders: list[tuple[float, float, float, float, float]] | None = None,
    ) -> NDArray[np.uint8]:
        """The part at each pose on a flat background, ``size`` = (width, height) px.

        ``occluders``: rectangles ``(u0, v0, u1, v1, grey)`` painted over the parts (e.g. a
        gripper finger), axis-aligned, full-image px; Gaussian noise ``noise`` grey levels
        (seeded) is added last.
        """
        w, h = size
        y, x = np.mgrid[0:h, 0:w].astype(np.float64)
        canvas = np.full((h, w), BACKGROUND)
        reach = float(np.abs(self.spots[:, :2]).max() + 4.0 * self.spots[:, 2].max())
        for u, v, angle, scale in poses:
            c, s = np.cos(angle), np.sin(angle)
            near = (np.abs(x - u) < reach * scale) & (np.abs(y - v) < reach * scale)
            dx, dy = x[near] - u, y[near] - v
            # Inverse of p -> scale R p: R^T d / scale.
            canvas[near] += self.texture((c * dx + s * dy) / scale, (-s * dx + c * dy) / scale)
        for u0, v0, u1, v1, grey in occluders or []:
            inside = (x >= u0) & (x < u1) & (y >= v0) & (y < v1)
            canvas[inside] = grey
        noisy = canvas + np.random.default_rng(seed).normal(0.0, noise, canvas.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def random_part(seed: int, *, spots: int = 40, spread: float = 26.0) -> TexturedPart:
    """A part with ``spots`` random Gaussian spots within ``spread`` px of its centre (sigma
    3..7 px, amplitude +-30..70 grey levels)."""
    rng = np.random.default_rng(seed)
    return TexturedPart(
        np.stack(
            [
                rng.uniform(-spread, spread, spots),
                rng.uniform(-spread, spread, spots),
                rng.uniform(3.0, 7.0, spots),
                rng.choice([-1.0, 1.0], spots) * rng.uniform(30.0, 70.0, spots),
            ],
            axis=1,
        )
    )
