"""Undoing linear motion blur along one image axis (Wiener deconvolution of a box blur).

A 1D code photographed while the camera or the part moves across its bars is smeared along
the scan line: the narrow spaces between wide bars never get light enough to be split from
them, and no binarizer recovers them (issue 19: a Code 128 label with about 4 px of blur).
Averaging along the bars only removes noise; what is lost is the high spatial frequency
across them, which a deconvolution restores where the blur kernel is roughly known.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = ["deblur_axis"]

GrayImage = NDArray[np.uint8]


def deblur_axis(
    gray: GrayImage,
    lengths_px: Sequence[int],
    *,
    axis: int = 1,
    noise_to_signal: float = 0.05,
) -> Iterator[tuple[int, GrayImage]]:
    """For each length of ``lengths_px``, in order: that length and ``gray`` (H, W) with a box
    motion blur of that many pixels along ``axis`` (1: along the rows, u; 0: along the
    columns, v) undone by a Wiener filter, stretched back to 0..255 between its 1st and 99th
    percentiles. A generator: a caller that stops at the first useful copy pays for no more
    (the image's spectrum is computed once, each copy costs one inverse transform).

    ``noise_to_signal`` is the Wiener filter's regularisation (the noise-to-signal power
    ratio, unitless): lower restores sharper edges and amplifies more noise.

    Raises ValueError for a length below 2 pixels, a non-positive ``noise_to_signal`` or an
    axis other than 0 or 1 (when the generator starts).
    """
    if any(length < 2 for length in lengths_px):
        raise ValueError(f"lengths_px must be >= 2 pixels, got {list(lengths_px)}")
    if noise_to_signal <= 0:
        raise ValueError(f"noise_to_signal must be > 0, got {noise_to_signal}")
    if axis not in (0, 1):
        raise ValueError(f"axis must be 0 or 1, got {axis}")
    img = np.asarray(gray, np.float32)
    if axis == 0:
        img = img.T
    n = img.shape[1]
    # Edge padding so that the circular convolution of the FFT does not wrap one side's grey
    # level into the other (a ring along the borders otherwise).
    pad = max(4 * max(lengths_px, default=2), n // 8)
    padded = np.pad(img, ((0, 0), (pad, pad)), mode="edge")
    m = padded.shape[1]
    spectrum = np.fft.rfft(padded, axis=1)  # float32 in, complex64 out
    for length in lengths_px:
        kernel = np.zeros(m, np.float32)
        kernel[:length] = 1.0 / length
        kernel = np.roll(kernel, -(length // 2))  # centred: the result is not shifted
        transfer = np.fft.rfft(kernel)
        gain = (np.conj(transfer) / (np.abs(transfer) ** 2 + noise_to_signal)).astype(np.complex64)
        restored = np.fft.irfft(spectrum * gain[None, :], n=m, axis=1)[:, pad : pad + n]
        # the stretch's levels from every 4th row: the percentiles of a full image cost as
        # much as the inverse transform
        low, high = np.percentile(restored[::4], [1.0, 99.0])
        scale = 255.0 / max(float(high - low), 1e-6)
        out = np.clip((restored - low) * scale, 0.0, 255.0).astype(np.uint8)
        yield length, np.ascontiguousarray(out.T if axis == 0 else out)
