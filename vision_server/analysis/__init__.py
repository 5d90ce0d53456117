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
- Calipers and measurement: :func:`find_edges`, :func:`find_pairs` on a :class:`Band` →
  :class:`Edge`, :class:`EdgePair`; :func:`measure` runs spec records (:class:`EdgeSpec`,
  :class:`WidthSpec`, :class:`CircleSpec`, :class:`LineSpec`, :class:`DistanceSpec`) →
  :class:`Measurement`, in :class:`PixelUnits`, :class:`ScaleUnits` (mm per px) or
  :class:`PlaneUnits` (mm through the intrinsics and a plane distance); fits in
  :mod:`.fit2d`.
- Errors: :class:`AnalysisError` and its kinds :class:`BadImageError`, :class:`RoiError`,
  :class:`TemplateError`, :class:`DepthError`, :class:`NotFoundError`.
"""

from .caliper import Band, Edge, EdgePair, find_edges, find_pairs
from .codes import SYMBOLOGIES, Code, Grade, read_codes
from .errors import AnalysisError, BadImageError, DepthError, NotFoundError, RoiError, TemplateError
from .locate import Feature, locate, locate_blobs, locate_circles, locate_template
from .measure import (
    CircleSpec,
    DistanceSpec,
    EdgeSpec,
    LineSpec,
    Measurement,
    WidthSpec,
    measure,
)
from .plane_units import PixelUnits, PlaneUnits, ScaleUnits
from .presence import MEASURES, PresenceResult, measure_presence, measure_presence_details
from .qr import QRCode, read_qr
from .qr_pose import QRPose, QRPoseQuality, qr_pose

__all__ = [
    "MEASURES",
    "Band",
    "CircleSpec",
    "DistanceSpec",
    "Edge",
    "EdgePair",
    "EdgeSpec",
    "LineSpec",
    "Measurement",
    "PixelUnits",
    "PlaneUnits",
    "ScaleUnits",
    "WidthSpec",
    "find_edges",
    "find_pairs",
    "measure",
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
