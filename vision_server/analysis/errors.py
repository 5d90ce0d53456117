"""Errors of the image-analysis functions. Each names its cause; the server maps them to
protocol errors (see :data:`PROTOCOL_CODES`)."""

from __future__ import annotations


class AnalysisError(ValueError):
    """Base: the analysis could not be done on this input."""


class BadImageError(AnalysisError):
    """Wrong dtype, shape or size, or an empty image."""


class RoiError(AnalysisError):
    """An ROI that does not lie inside the image, or is empty."""


class TemplateError(AnalysisError):
    """A template that is missing, unreadable, or larger than the image."""


class DepthError(AnalysisError):
    """Depth that cannot support the measurement (e.g. a QR corner with no valid depth)."""


class NotFoundError(AnalysisError):
    """What was looked for is not in the image (e.g. no QR code with the expected text)."""
