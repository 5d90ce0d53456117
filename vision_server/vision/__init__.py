"""vision_server.vision: the image analysis behind the inspections, as pure functions.

No knowledge of the protocol or of YAML. Conventions: docs/conventions.md (pixels ``(u, v)`` =
OpenCV ``(x, y)``, ROI ``[u, v, width, height]``, metres, depth uint16 mm with 0 = no depth,
transforms ``b_from_a`` 4x4 float64, QR corners c0..c3 clockwise from the top-left as printed).

Public API:

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
from vision_server.vision.qr import DECODERS, QrCode, read_qr
from vision_server.vision.qr_pose import QrPose, QrPoseQuality, qr_pose

__all__ = [
    "DECODERS",
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
    "qr_pose",
    "read_qr",
]
