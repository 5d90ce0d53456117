"""Image analysis behind the inspections: pure functions, image first, options keyword-only.

Coordinates are (u, v) = (column, row) in full-image pixels, angles in radians, depth in
millimetres (uint16), poses as 4x4 ``camera_from_qr``; see docs/conventions.md.

Public API:

- Locate: :func:`locate` (dispatch), :func:`locate_template`, :func:`locate_circles`,
  :func:`locate_blobs` → :class:`Feature`.
- Presence: :func:`measure_presence` (one number), :func:`measure_presence_details`
  → :class:`PresenceResult`; ``MEASURES``.
- QR: :func:`read_qr` → :class:`QRCode`; :func:`qr_pose` → :class:`QRPose` with
  :class:`QRPoseQuality`.
- Codes (every common 2D and 1D symbology): :func:`read_codes` → :class:`Code` with its
  :class:`Grade`; ``SYMBOLOGIES``.
- Errors: :class:`AnalysisError` and its kinds :class:`BadImageError`, :class:`RoiError`,
  :class:`TemplateError`, :class:`DepthError`, :class:`NotFoundError`.
"""

from .codes import SYMBOLOGIES, Code, Grade, read_codes
from .errors import AnalysisError, BadImageError, DepthError, NotFoundError, RoiError, TemplateError
from .locate import Feature, locate, locate_blobs, locate_circles, locate_template
from .presence import MEASURES, PresenceResult, measure_presence, measure_presence_details
from .qr import QRCode, read_qr
from .qr_pose import QRPose, QRPoseQuality, qr_pose

__all__ = [
    "MEASURES",
    "SYMBOLOGIES",
    "Code",
    "Grade",
    "AnalysisError",
    "BadImageError",
    "DepthError",
    "Feature",
    "NotFoundError",
    "PresenceResult",
    "QRCode",
    "QRPose",
    "QRPoseQuality",
    "RoiError",
    "TemplateError",
    "locate",
    "locate_blobs",
    "locate_circles",
    "locate_template",
    "measure_presence",
    "measure_presence_details",
    "qr_pose",
    "read_codes",
    "read_qr",
]
