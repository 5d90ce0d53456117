"""OpenCV's own image-size limits, tied to the server's ``max_image_pixels`` (the second fence).

The first fence is :func:`protocol.array_from_payload`: it reads a PNG/JPEG header and refuses
before decoding. This module makes OpenCV's decoders enforce the same limit on *their* reading of
the header, so that if the two ever disagree the decoder still cannot allocate beyond it: OpenCV
checks ``OPENCV_IO_MAX_IMAGE_PIXELS`` (and ``_WIDTH``, ``_HEIGHT``) after its decoder has read the
header and before it allocates the image, and fails with ``cv2.error`` instead.

**OpenCV reads these variables once, when the cv2 library is loaded** (they are static
initialisers in imgcodecs' ``loadsave.cpp``; checked with OpenCV 5.0: setting them after
``import cv2``, even before the first decode, has no effect). So:

- importing :mod:`vision_server` calls :func:`install_default` *before* anything imports cv2; it
  sets the default limit unless the environment already sets one;
- ``vision-server serve`` calls :func:`ensure` with the configured limit: when OpenCV loaded with
  a different one, the process re-executes itself once with the right environment (same PID).

This module must not import cv2 (or anything that does) at module level.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping, Sequence

log = logging.getLogger(__name__)

PIXELS_VAR = "OPENCV_IO_MAX_IMAGE_PIXELS"
WIDTH_VAR = "OPENCV_IO_MAX_IMAGE_WIDTH"
HEIGHT_VAR = "OPENCV_IO_MAX_IMAGE_HEIGHT"
DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096
"""Equal to ``ServerSettings.max_image_pixels``'s default (a test keeps them equal)."""
_REEXEC_MARK = "CELLVISION_DECODER_LIMITS_REEXEC"

_loaded_with: int | None = None
"""The pixel limit OpenCV was loaded with, when this process knows it (None: unknown)."""


def opencv_environment(max_pixels: int) -> dict[str, str]:
    """The variables that make OpenCV refuse images of more than ``max_pixels`` pixels.

    A side is at most ``max_pixels`` too (OpenCV's default side limit is 2**20, larger than
    useful once the product is bounded).
    """
    if max_pixels <= 0:
        raise ValueError(f"max_pixels must be positive, got {max_pixels}")
    value = str(max_pixels)
    return {PIXELS_VAR: value, WIDTH_VAR: value, HEIGHT_VAR: value}


def _configured(environ: Mapping[str, str]) -> int | None:
    """The pixel limit ``environ`` gives OpenCV, if the three variables say one consistent
    thing (a side limit below the pixel limit is stricter, which is fine)."""
    try:
        pixels = int(environ[PIXELS_VAR])
        width = int(environ.get(WIDTH_VAR, str(1 << 20)))
        height = int(environ.get(HEIGHT_VAR, str(1 << 20)))
    except (KeyError, ValueError):
        return None
    return pixels if pixels > 0 and width > 0 and height > 0 else None


def install_default() -> None:
    """Give OpenCV the default limit before it loads, unless the environment already sets one.

    Called by ``vision_server/__init__.py`` before any import of cv2. When cv2 is already
    loaded (it was imported before vision_server), the limit it loaded with is unknown.
    """
    global _loaded_with
    if "cv2" in sys.modules:
        return
    if _configured(os.environ) is None:
        os.environ.update(opencv_environment(DEFAULT_MAX_IMAGE_PIXELS))
    _loaded_with = _configured(os.environ)


def loaded_limit() -> int | None:
    """The pixel limit OpenCV applies in this process, if known (see :func:`install_default`)."""
    return _loaded_with


def ensure(
    max_pixels: int,
    *,
    argv: Sequence[str] | None = None,
    process_env: Mapping[str, str] | None = None,
) -> bool:
    """Make OpenCV's pixel limit ``max_pixels``; True when it holds.

    With ``argv`` (the process's full command line, ``sys.orig_argv``) a process whose OpenCV
    loaded with another limit, or that lacks a variable of ``process_env`` (read only at
    start, such as ``MALLOC_ARENA_MAX``), re-executes itself once with the right environment:
    this does not return then. Without it (a server embedded in another program, tests), a
    mismatch is logged and False returned; the server's own header check still applies.
    """
    missing = {k: v for k, v in (process_env or {}).items() if k not in os.environ}
    if loaded_limit() == max_pixels and not missing:
        return True
    wanted = {**opencv_environment(max_pixels), **missing}
    if argv and os.environ.get(_REEXEC_MARK) != str(max_pixels):
        # Flush what was printed so far: exec replaces the process and its buffers.
        sys.stdout.flush()
        sys.stderr.flush()
        env = {**os.environ, **wanted, _REEXEC_MARK: str(max_pixels)}
        os.execve(sys.executable, list(argv), env)
    if loaded_limit() == max_pixels:
        return True  # only a start-time variable is missing: nothing unsafe about that
    log.warning(
        "OpenCV's decoders were loaded with an image limit of %s pixels, the server's "
        "max_image_pixels is %d; start the process with %s to make them agree",
        loaded_limit() or "an unknown number of",
        max_pixels,
        " ".join(f"{k}={v}" for k, v in wanted.items()),
    )
    return False
