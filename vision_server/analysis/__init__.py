"""Image analysis behind the inspections: pure functions, image first, options keyword-only.

Coordinates are (u, v) = (column, row) in full-image pixels; see docs/conventions.md.
"""

from .errors import AnalysisError, BadImageError, DepthError, NotFoundError, RoiError, TemplateError

__all__ = [
    "AnalysisError",
    "BadImageError",
    "DepthError",
    "NotFoundError",
    "RoiError",
    "TemplateError",
]
