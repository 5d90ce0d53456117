"""vision_server.vision: the image analysis behind the inspections, as pure functions.

No knowledge of the protocol or of YAML. Conventions: docs/conventions.md (pixels ``(u, v)`` =
OpenCV ``(x, y)``, ROI ``[u, v, width, height]``, metres, depth uint16 mm with 0 = no depth,
transforms ``b_from_a`` 4x4 float64, QR corners c0..c3 clockwise from the top-left as printed).

Public API:

- Locate: ``locate(image, *, method, **options)`` dispatching to
  ``locate_template(image, template, *, roi, min_score, max_count, angle_range, angle_step,
  min_distance)``, ``locate_circles(image, *, roi, radius_range, min_score, max_count, ...)``,
  ``locate_blobs(image, *, roi, threshold, polarity, area_range, min_circularity, max_count)``
  -> ``tuple[Feature, ...]`` (best first, full-image sub-pixel ``u, v``).
- Presence: ``measure_presence(image, *, measure, roi, threshold, canny, polarity, area_range,
  template) -> PresenceMeasurement`` (``MEASURES`` lists the measures).
- Overlay: ``draw_overlay(image, *, roi, features, quads, verdict, passed) -> BGR uint8``.
- QR: ``read_qr(image, *, roi, expect, decoders, preprocess, refine) -> tuple[QrCode, ...]``.
- QR pose: ``qr_pose(depth_frames, corners, intrinsics, *, method, side_m, ...) -> QrPose``
  (``camera_from_qr`` + ``QrPoseQuality``).
- Errors (``errors``): ``VisionError`` > ``BadImageError``, ``RoiError``, ``ParameterError``,
  ``TemplateError``, ``InspectionFailed`` > ``DepthError``; each has a protocol ``code``.
- Validation: ``check_image``, ``as_gray``, ``check_depth``, ``check_roi``.
"""

from vision_server.vision._checks import as_gray, check_depth, check_image, check_roi
from vision_server.vision.errors import (
    BadImageError,
    DepthError,
    InspectionFailed,
    ParameterError,
    RoiError,
    TemplateError,
    VisionError,
)
from vision_server.vision.locate import (
    Feature,
    locate,
    locate_blobs,
    locate_circles,
    locate_template,
)
from vision_server.vision.overlay import draw_overlay
from vision_server.vision.presence import MEASURES, PresenceMeasurement, measure_presence
from vision_server.vision.qr import DECODERS, QrCode, read_qr
from vision_server.vision.qr_pose import QrPose, QrPoseQuality, qr_pose

__all__ = [
    "DECODERS",
    "MEASURES",
    "Feature",
    "PresenceMeasurement",
    "BadImageError",
    "DepthError",
    "InspectionFailed",
    "ParameterError",
    "QrCode",
    "QrPose",
    "QrPoseQuality",
    "RoiError",
    "TemplateError",
    "VisionError",
    "as_gray",
    "check_depth",
    "check_image",
    "check_roi",
    "draw_overlay",
    "locate",
    "locate_blobs",
    "locate_circles",
    "locate_template",
    "measure_presence",
    "qr_pose",
    "read_qr",
]
