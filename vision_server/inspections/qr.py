"""``qr``: read a QR code (text and the four corners c0..c3), optionally expecting a text.

``corners: subpixel`` (the default) refines the corners to a fraction of a pixel, which costs
about three times zxing-cpp's decode; ``corners: decoder`` reports the decoder's own corner
estimates (whole pixels, c0..c3 in the same order) for a check that needs the payload only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from yamlfile import Node, one_of, string

from ..analysis import (
    AnalysisError,
    Expect,
    NotFoundError,
    PatternError,
    compile_pattern,
    read_qr,
)
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
from .kinds import Data, ResultKind, points

RED = (0, 0, 255)


@dataclass(frozen=True)
class QRInspection(Configured):
    common: Common
    expect: Expect
    subpixel: bool = True  # ``corners: subpixel``; False: ``corners: decoder``

    type = "qr"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        try:
            codes = read_qr(
                image.color, roi=self.common.roi, expect=self.expect, refine=self.subpixel
            )
        except NotFoundError as exc:
            codes, reason = [], str(exc)
        except AnalysisError as exc:
            raise analysis_failed(self.common.name, exc) from None
        data: dict[str, object]
        if codes:
            best = codes[0]
            data = {
                "found": True,
                "text": best.text,
                "corners": [[float(u), float(v)] for u, v in best.corners],
                "decoder": best.decoder,
                "codes": [{"text": c.text, "corners": c.corners.tolist()} for c in codes],
            }
        else:
            data = {"found": False, "reason": reason}
        picture = None
        if overlay:
            picture = overlay_base(image.color, self.common.roi)
            for code in codes:
                pts = np.round(code.corners).astype(np.int32)
                cv2.polylines(picture, [pts], True, RED, 2)
                for index, (u, v) in enumerate(pts):
                    draw_text(picture, f"c{index}", (int(u) + 4, int(v) - 4), RED)
            draw_verdict(picture, bool(codes), codes[0].text if codes else "no code")
        return InspectionOutcome(bool(codes), data, picture)


def parse_expect(node: Node) -> Expect:
    """``expect: TEXT`` (exact) or ``expect: {regex: PATTERN}`` (full match, RE2 syntax:
    matched in time linear in the payload, :mod:`vision_server.analysis.expect`)."""
    if "expect" not in node:
        node.take("expect", string, None)
        return None
    raw = node.data["expect"]
    if isinstance(raw, dict):
        sub = node.sub("expect")
        pattern = sub.take("regex", string)
        sub.finish()
        try:
            return compile_pattern(pattern)
        except PatternError as exc:
            raise sub.error(f"bad regular expression: {exc}", "regex") from None
    return node.take("expect", string)


def parse_qr(node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]) -> QRInspection:
    common = parse_common(node, "qr", cameras)
    expect = parse_expect(node)
    corners = node.take("corners", one_of("subpixel", "decoder"), "subpixel")
    return QRInspection(common, expect, subpixel=corners == "subpixel")


def _qr_expected(data: Data) -> dict[str, Any]:
    if not data.get("found"):
        return {}
    return {"text": data["text"], "corners": points(data["corners"])}


def _qr_summary(data: Data) -> dict[str, float]:
    return {"found": 1.0 if data.get("found") else 0.0}


RESULTS = ResultKind(
    ("text", "corners"), _qr_expected, _qr_summary, units={"found": "1 found, 0 not"}
)
"""A QR result: the text and corners of the code found (nothing when none was)."""
