"""``code``: read a 2D or 1D code of the configured symbologies, verify its payload and grade it.

The ``qr`` type stays as it is (QR only, printed corner order c0..c3, pyzbar and OpenCV as
fallbacks, used by ``qr_pose``); ``code`` reads every common symbology through zxing-cpp and
reports the symbol's own corner order (see :mod:`vision_server.analysis.codes`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from yamlfile import Node, non_negative, one_of

from ..analysis import SYMBOLOGIES, AnalysisError, Code, Expect, Grade, NotFoundError, read_codes
from ..cameras import CameraSettings
from .base import (
    Common,
    Configured,
    analysis_failed,
    draw_text,
    draw_verdict,
    overlay_base,
    parse_common,
)
from .contract import InspectionInput, InspectionOutcome
from .kinds import Data, ResultKind, as_number, points
from .qr import parse_expect

RED = (0, 0, 255)
GRADE_KEYS = ("module_px", "contrast", "decode_margin", "quiet_zone_modules")


@dataclass(frozen=True)
class CodeInspection(Configured):
    common: Common
    symbologies: tuple[str, ...]
    expect: Expect
    min_grade: tuple[tuple[str, float], ...]
    """(grade name, lowest value that passes), in :data:`GRADE_KEYS` order."""

    type = "code"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        try:
            codes = read_codes(
                image.color, symbologies=self.symbologies, roi=self.common.roi, expect=self.expect
            )
        except NotFoundError as exc:
            codes, reason = [], str(exc)
        except AnalysisError as exc:
            raise analysis_failed(self.common.name, exc) from None
        data: dict[str, object]
        passed = bool(codes)
        if codes:
            best = codes[0]
            data = {"found": True, **_code_data(best)}
            data["codes"] = [
                {
                    "text": c.text,
                    "text_hri": c.text_hri,
                    "symbology": c.symbology,
                    "corners": c.corners.tolist(),
                }
                for c in codes
            ]
            low = below_grade(best.grade, self.min_grade)
            if low:
                passed = False
                data["reason"] = "grade below the minimum: " + "; ".join(low)
        else:
            data = {"found": False, "reason": reason}
        picture = None
        if overlay:
            picture = overlay_base(image.color, self.common.roi)
            for code in codes:
                pts = np.round(code.corners).astype(np.int32)
                cv2.polylines(picture, [pts], True, RED, 2)
                u, v = pts[0]
                label = f"{code.symbology}: {code.text_hri[:40]}"
                draw_text(picture, label, (int(u), int(v) - 6), RED)
            draw_verdict(picture, passed, codes[0].text_hri[:40] if codes else "no code")
        return InspectionOutcome(passed, data, picture)


def _code_data(code: Code) -> dict[str, object]:
    g = code.grade
    return {
        "text": code.text,
        "text_hri": code.text_hri,
        "symbology": code.symbology,
        "format": code.format,
        "corners": [[float(u), float(v)] for u, v in code.corners],
        "bbox": list(code.bbox),
        "orientation_deg": code.orientation_deg,
        "inverted": code.inverted,
        "mirrored": code.mirrored,
        "decoder": code.decoder,
        "grade": {
            "module_px": round(g.module_px, 3),
            "contrast": round(g.contrast, 4),
            "decode_margin": round(g.decode_margin, 4),
            "quiet_zone_modules": (
                None if g.quiet_zone_modules is None else round(g.quiet_zone_modules, 2)
            ),
        },
    }


def below_grade(grade: Grade, minimum: tuple[tuple[str, float], ...]) -> list[str]:
    low = []
    for key, lowest in minimum:
        value = getattr(grade, key)
        if value is None or value < lowest:
            shown = "unknown" if value is None else f"{value:.3g}"
            low.append(f"{key} {shown} < {lowest:g}")
    return low


def parse_min_grade(node: Node) -> tuple[tuple[str, float], ...]:
    sub = node.sub_optional("min_grade")
    if sub is None:
        return ()
    out = []
    for key in GRADE_KEYS:
        value = sub.take(key, non_negative, None)
        if value is not None:
            out.append((key, float(value)))
    sub.finish()
    return tuple(out)


def parse_code(node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]) -> CodeInspection:
    common = parse_common(node, "code", cameras)
    return CodeInspection(
        common, parse_symbologies(node), parse_expect(node), parse_min_grade(node)
    )


def parse_symbologies(node: Node) -> tuple[str, ...]:
    """``symbologies:``, a non-empty list of :data:`SYMBOLOGIES` (absent: every one)."""
    symbologies: tuple[str, ...] = tuple(SYMBOLOGIES)
    if node.has("symbologies"):
        raw = node.data["symbologies"]
        if not isinstance(raw, list) or not raw:
            raise node.error(
                f"expected a non-empty list of symbologies (any of {', '.join(SYMBOLOGIES)})",
                "symbologies",
            )
        check = one_of(*SYMBOLOGIES)
        names = []
        for index, value in enumerate(raw):
            try:
                names.append(check(value))
            except ValueError as exc:
                raise node.error(f"symbologies[{index}]: {exc}", "symbologies") from None
        node.take("symbologies", lambda value: value)
        symbologies = tuple(dict.fromkeys(names))
    return symbologies


def _code_expected(data: Data) -> dict[str, Any]:
    if not data.get("found"):
        return {}
    return {"text": data["text"], "corners": points(data["corners"])}


def _code_summary(data: Data) -> dict[str, float]:
    grade = data.get("grade") or {}
    return {
        "found": 1.0 if data.get("found") else 0.0,
        "module_px": as_number(grade, "module_px"),
        "decode_margin": as_number(grade, "decode_margin"),
    }


RESULTS = ResultKind(
    ("text", "corners"),
    _code_expected,
    _code_summary,
    units={"found": "1 found, 0 not", "module_px": "px", "decode_margin": "0..1"},
)
"""A code result: payload and corners of the first code read (nothing when none)."""
