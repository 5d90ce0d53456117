"""Typed errors of the image-analysis functions.

Every error names its cause in its message. The server maps each class to a protocol error code
(``code``): bad input -> ``BAD_IMAGE`` / ``BAD_REQUEST``; a measurement that could not be made
-> ``INSPECTION_FAILED``.
"""

from __future__ import annotations

__all__ = [
    "BadImageError",
    "DepthError",
    "InspectionFailed",
    "ParameterError",
    "RoiError",
    "TemplateError",
    "VisionError",
]


class VisionError(Exception):
    """Base class of every error raised by ``vision_server.vision``."""

    code = "INSPECTION_FAILED"


class BadImageError(VisionError, ValueError):
    """An image has the wrong dtype, shape or number of channels, is empty or is corrupt."""

    code = "BAD_IMAGE"


class RoiError(VisionError, ValueError):
    """A region of interest is malformed, empty or not inside the image."""

    code = "BAD_REQUEST"


class ParameterError(VisionError, ValueError):
    """An option has an invalid value (e.g. a negative radius, min > max)."""

    code = "BAD_REQUEST"


class TemplateError(VisionError, ValueError):
    """A template image is missing, unreadable, empty or larger than the searched region."""

    code = "BAD_REQUEST"


class InspectionFailed(VisionError):
    """The measurement could not be made on a valid input (e.g. no QR code found)."""

    code = "INSPECTION_FAILED"


class DepthError(InspectionFailed):
    """Depth data are missing or insufficient (e.g. a QR corner has no valid depth)."""

    code = "INSPECTION_FAILED"
