"""Configured inspections: each type reads its keys from the configuration and runs the
image analysis of :mod:`vision_server.analysis` on the images of one request.

Types: ``locate`` (feature locate: template, circle, blob), ``presence`` (ROI presence check),
``qr`` (QR read), ``qr_pose`` (pose of a QR code from colour + depth).

Public API: :func:`parse_inspection` (configuration → an :class:`~vision_server.catalog.
Inspection`), ``INSPECTION_TYPES``, ``RESULT_KINDS`` (each type's :class:`ResultKind`: its
golden expectations and summary values), and the classes :class:`LocateInspection`,
:class:`PresenceInspection`, :class:`QRInspection`, :class:`QRPoseInspection`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

from ..cameras import CameraSettings
from ..catalog import Inspection
from ..configfile import Node, one_of
from . import locate, presence, qr, qr_pose
from .kinds import ResultKind
from .locate import LocateInspection, parse_locate
from .presence import PresenceInspection, parse_presence
from .qr import QRInspection, parse_qr
from .qr_pose import QRPoseInspection, parse_qr_pose

Parser = Callable[[Node, Path, Mapping[str, CameraSettings]], Inspection]

INSPECTION_TYPES: dict[str, Parser] = {
    "locate": parse_locate,
    "presence": parse_presence,
    "qr": parse_qr,
    "qr_pose": parse_qr_pose,
}

RESULT_KINDS: dict[str, ResultKind] = {
    "locate": locate.RESULTS,
    "presence": presence.RESULTS,
    "qr": qr.RESULTS,
    "qr_pose": qr_pose.RESULTS,
}
"""Each type's result shape (golden expectations, summary values), declared by the type."""

InspectionSpec = Inspection
"""A configured inspection is its own specification: frozen, with its parameters."""


def parse_inspection(
    node: Node, *, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> Inspection:
    """Read one entry of ``inspections:``; raises ConfigError naming file, line and key."""
    kind = node.take("type", one_of(*INSPECTION_TYPES))
    inspection = INSPECTION_TYPES[kind](node, base_dir, cameras)
    node.finish()
    return inspection


__all__ = [
    "INSPECTION_TYPES",
    "RESULT_KINDS",
    "InspectionSpec",
    "LocateInspection",
    "PresenceInspection",
    "QRInspection",
    "QRPoseInspection",
    "ResultKind",
    "parse_inspection",
]
