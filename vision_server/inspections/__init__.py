"""Configured inspections: each type reads its keys from the configuration and runs the
image analysis of :mod:`vision_server.analysis` on the images of one request.

Types: ``locate`` (feature locate: template, circle, blob), ``presence`` (ROI presence check),
``qr`` (QR read), ``code`` (DataMatrix, QR, Aztec, PDF417 and 1D codes: read, verify,
grade), ``qr_pose`` (pose of a QR code from colour + depth), ``calibration_board``
(corners of a ChArUco board or chessboard, for camera calibration), ``job`` (named steps:
locate, fixture, presence, code, with ROIs that move with the part and a verdict expression),
``caliper`` (edges, widths, circles, lines and distances with tolerances, in px or mm),
``anomaly`` (a score against a model trained from good images, with a heat map; also a job
step).

Public API: the contract every type implements (:class:`Inspection`, run on an
:class:`InspectionInput`, giving an :class:`InspectionOutcome`; :mod:`.contract`),
:func:`parse_inspection` (a configuration node → an :class:`Inspection`),
``INSPECTION_TYPES``, a job's ``STEP_TYPES``, a caliper's measurement ``CALIPER_KINDS``,
``RESULT_KINDS`` (each type's :class:`ResultKind`: its
golden expectations and summary values), and the classes :class:`LocateInspection`,
:class:`PresenceInspection`, :class:`QRInspection`, :class:`CodeInspection`,
:class:`QRPoseInspection`, :class:`JobInspection`,
:class:`CalibrationBoardInspection`, :class:`CaliperInspection`, :class:`AnomalyInspection`
(with its :class:`AnomalySettings`); what the configuration's
``output:`` and the other rooms need of them (:func:`numbers_by_position`, ...);
:func:`result_shapes` (a result as shapes in image pixels, for the console's online view).

Inspections read their keys through :mod:`yamlfile`'s nodes; the node's owner (the
configuration) decides the error type they raise.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path

from yamlfile import Node, one_of, positive_int

from ..cameras import CameraSettings
from . import anomaly, calibration_board, caliper, code, job, locate, presence, qr, qr_pose
from .anomaly import AnomalyInspection, AnomalySettings, parse_anomaly
from .base import Configured
from .calibration_board import CalibrationBoardInspection, parse_calibration_board
from .caliper import SUMMARY_VALUES, CaliperInspection, parse_caliper
from .caliper_config import KINDS as CALIPER_KINDS
from .code import CodeInspection, parse_code
from .contract import Inspection, InspectionInput, InspectionOutcome
from .graphics import MAX_SHAPES, result_shapes
from .job import STEP_TYPES, JobInspection, StepSkipped, parse_job, step_summary_values
from .kinds import ResultKind
from .locate import LocateInspection, parse_locate
from .output import (
    MAX_FIELDS,
    POSE,
    OutputField,
    OutputFormat,
    default_output,
    numbers_by_position,
    parse_output,
)
from .presence import MEASURE_RANGES, PresenceInspection, parse_presence
from .qr import QRInspection, parse_qr
from .qr_pose import QRPoseInspection, parse_qr_pose

Parser = Callable[[Node, Path, Mapping[str, CameraSettings]], Inspection]

INSPECTION_TYPES: dict[str, Parser] = {
    "locate": parse_locate,
    "presence": parse_presence,
    "qr": parse_qr,
    "code": parse_code,
    "qr_pose": parse_qr_pose,
    "calibration_board": parse_calibration_board,
    "job": parse_job,
    "caliper": parse_caliper,
    "anomaly": parse_anomaly,
}

RESULT_KINDS: dict[str, ResultKind] = {
    "locate": locate.RESULTS,
    "presence": presence.RESULTS,
    "qr": qr.RESULTS,
    "code": code.RESULTS,
    "qr_pose": qr_pose.RESULTS,
    "calibration_board": calibration_board.RESULTS,
    "job": job.RESULTS,
    "caliper": caliper.RESULTS,
    "anomaly": anomaly.RESULTS,
}
"""Each type's result shape (golden expectations, summary values), declared by the type."""

InspectionSpec = Inspection
"""A configured inspection is its own specification: frozen, with its parameters."""


def parse_inspection(
    node: Node, *, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> Inspection:
    """Read one entry of ``inspections:``; raises ConfigError naming file, line and key."""
    kind = node.take("type", one_of(*INSPECTION_TYPES))
    # What the line protocol calls it and answers (the same for every type), read first so
    # that the type's parser sees only its own keys.
    number = node.take("number", positive_int, None)
    given = node.has("output")
    output_node = node.sub("output")
    camera = node.data.get("camera") if isinstance(node.data, dict) else None
    settings = cameras.get(camera) if isinstance(camera, str) else None
    inspection = INSPECTION_TYPES[kind](node, base_dir, cameras)
    # read after the inspection: a job's output may name its steps' values (STEP.VALUE)
    extra = step_summary_values(inspection) if isinstance(inspection, JobInspection) else None
    output = (
        parse_output(
            output_node,
            RESULT_KINDS[kind],
            kind,
            camera=str(camera),
            settings=settings,
            extra=extra,
        )
        if given
        else None
    )
    node.finish()
    if isinstance(inspection, Configured) and (number is not None or output is not None):
        common = replace(inspection.common, number=number, output=output)
        inspection = replace(inspection, common=common)  # type: ignore[type-var]
    return inspection


__all__ = [
    "AnomalyInspection",
    "AnomalySettings",
    "CALIPER_KINDS",
    "STEP_TYPES",
    "Inspection",
    "InspectionInput",
    "InspectionOutcome",
    "CalibrationBoardInspection",
    "CaliperInspection",
    "CodeInspection",
    "INSPECTION_TYPES",
    "InspectionSpec",
    "JobInspection",
    "LocateInspection",
    "MAX_FIELDS",
    "MAX_SHAPES",
    "MEASURE_RANGES",
    "OutputField",
    "OutputFormat",
    "POSE",
    "PresenceInspection",
    "QRInspection",
    "QRPoseInspection",
    "RESULT_KINDS",
    "ResultKind",
    "SUMMARY_VALUES",
    "StepSkipped",
    "default_output",
    "numbers_by_position",
    "parse_inspection",
    "result_shapes",
]
