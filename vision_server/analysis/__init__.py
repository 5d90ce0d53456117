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
- Anomaly detection trained from good images (:mod:`.anomaly`): :func:`train_model` →
  :class:`AnomalyModel` (``score`` → :class:`AnomalyScore`) and :class:`TrainingReport`;
  the model file (:func:`save_model`, :func:`load_model`, :func:`model_bytes`,
  :func:`model_from_bytes`); ``ANOMALY_METHODS``, ``MIN_GOOD_IMAGES``; :class:`AnomalyError`,
  :class:`WeightsError`.
- Errors: :class:`AnalysisError` and its kinds :class:`BadImageError`, :class:`RoiError`,
  :class:`TemplateError`, :class:`DepthError`, :class:`NotFoundError`.
"""

from .anomaly import MAX_IMAGES as MAX_GOOD_IMAGES_TRAINED
from .anomaly import METHODS as ANOMALY_METHODS
from .anomaly import MIN_IMAGES as MIN_GOOD_IMAGES
from .anomaly import (
    AnomalyError,
    AnomalyModel,
    AnomalyScore,
    TrainingReport,
    WeightsError,
    image_digest,
    load_model,
    model_bytes,
    model_from_bytes,
    save_model,
    train_model,
)
from .board import BOARD_KINDS, DICTIONARIES, BoardSpec, detect_board
from .caliper import POLARITIES, Band, Edge, EdgePair, find_edges, find_pairs
from .codes import SYMBOLOGIES, Code, Grade, read_codes
from .depth_registration import fit_depth_registration, registration_advice
from .errors import AnalysisError, BadImageError, DepthError, NotFoundError, RoiError, TemplateError
from .expect import Expect, Pattern, PatternError, compile_pattern
from .locate import (
    CENTRES,
    MAX_SCALE,
    MIN_SCALE,
    Feature,
    Polarity,
    Rejection,
    circle_margin_px,
    locate,
    locate_blobs,
    locate_circles,
    locate_template,
)
from .measure import (
    CircleSpec,
    DistanceSpec,
    EdgeSpec,
    LineSpec,
    Measurement,
    Spec,
    WidthSpec,
    measure,
)
from .plane_units import PixelUnits, PlaneUnits, ScaleUnits, Units
from .presence import MEASURES, PresenceResult, measure_presence, measure_presence_details
from .qr import QRCode, read_qr
from .qr_pose import UNCHECKED_SCALE_STD, UNCHECKED_SHIFT_STD_PX, QRPose, QRPoseQuality, qr_pose

__all__ = [
    "ANOMALY_METHODS",
    "MAX_GOOD_IMAGES_TRAINED",
    "MIN_GOOD_IMAGES",
    "AnomalyError",
    "AnomalyModel",
    "AnomalyScore",
    "TrainingReport",
    "WeightsError",
    "image_digest",
    "load_model",
    "model_bytes",
    "model_from_bytes",
    "save_model",
    "train_model",
    "Expect",
    "Pattern",
    "PatternError",
    "compile_pattern",
    "AnalysisError",
    "BOARD_KINDS",
    "BadImageError",
    "Band",
    "BoardSpec",
    "CENTRES",
    "CircleSpec",
    "Code",
    "DICTIONARIES",
    "DepthError",
    "DistanceSpec",
    "Edge",
    "EdgePair",
    "EdgeSpec",
    "Feature",
    "Grade",
    "LineSpec",
    "MAX_SCALE",
    "MEASURES",
    "MIN_SCALE",
    "Measurement",
    "NotFoundError",
    "POLARITIES",
    "PixelUnits",
    "PlaneUnits",
    "Polarity",
    "PresenceResult",
    "QRCode",
    "QRPose",
    "QRPoseQuality",
    "Rejection",
    "RoiError",
    "SYMBOLOGIES",
    "ScaleUnits",
    "Spec",
    "TemplateError",
    "UNCHECKED_SCALE_STD",
    "UNCHECKED_SHIFT_STD_PX",
    "Units",
    "WidthSpec",
    "circle_margin_px",
    "detect_board",
    "find_edges",
    "find_pairs",
    "fit_depth_registration",
    "locate",
    "locate_blobs",
    "locate_circles",
    "locate_template",
    "measure",
    "measure_presence",
    "measure_presence_details",
    "qr_pose",
    "read_codes",
    "read_qr",
    "registration_advice",
]
