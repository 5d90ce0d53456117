"""Reading 2D and 1D codes (DataMatrix, QR, Micro QR, Aztec, PDF417, Code 128, Code 39, EAN/UPC,
ITF, GS1 DataBar) with zxing-cpp, escalating to preprocessed copies only when nothing is read.

:func:`read_codes` returns :class:`Code` objects in full-image pixels ``(u, v)``. ``corners``
are the symbol's four corners in symbol order as zxing-cpp reports them (top-left, top-right,
bottom-right, bottom-left of the symbol as printed, for a 1D code the ends of its scan line
pair); ``bbox`` is the axis-aligned box around them.

Payloads. ``text`` is the payload exactly as encoded (zxing-cpp's plain text mode): GS1 and
ISO/IEC 15434 separators (GS 0x1D, RS 0x1E, EOT 0x04) and every other control character are
kept. ``text_hri`` beside it is for people: each control character spelled ``<GS>``, ``<RS>``…

Escalation. The plain grey image is read first; only when nothing is read (or nothing matching
``expect``) pyzbar reads it for QR codes (where QR is wanted: zbar reads some that zxing-cpp
misses; ``orientation_deg`` is then 0, not measured), then the preprocessed copies of
:data:`ESCALATION` are tried, in order, and the first that reads something wins: the inverted
image (zxing-cpp retries light-on-dark matrix codes by itself, not 1D codes or PDF417), a
global-histogram binarizer instead of the local one, upscaling (small images) or downscaling
(large ones), sharpening, smoothing and a white border (a symbol touching the image edge has
no quiet zone); for 1D codes, copies with a motion blur across the bars undone
(:mod:`vision_server.analysis.deblur`, along the rows then the columns); last, where the
image's border is dark, :func:`_reframed` copies (a symbol without a light quiet zone whose
edge modules merge with a dark surround). Each code says
which copy read it (``decoder``).

Grading (:class:`Grade`, estimates from the image, not an ISO 15415/15416 verification):
``module_px``, ``contrast``, ``decode_margin`` and ``quiet_zone_modules``, computed in
:mod:`vision_server.analysis.code_grade`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import zxingcpp
from numpy.typing import NDArray
from pyzbar import pyzbar

from .code_grade import Grade, grade_code, is_inverted
from .deblur import deblur_axis
from .errors import NotFoundError
from .expect import Expect, describe, matches
from .qr import crop_for_code, gray_for_code, order_corners

MIN_SIDE_PX = 8
"""An image or ROI smaller than this a side holds no readable code (a 1D code's bars, the
smallest Micro QR)."""

__all__ = [
    "SYMBOLOGIES",
    "Code",
    "Grade",
    "human_readable",
    "read_codes",
]

FloatArray = NDArray[np.float64]
GrayImage = NDArray[np.uint8]

_F = zxingcpp.BarcodeFormat
SYMBOLOGIES: dict[str, tuple[zxingcpp.BarcodeFormat, ...]] = {
    "datamatrix": (_F.DataMatrix,),
    "qr": (_F.QRCode,),
    "micro_qr": (_F.MicroQRCode,),
    "aztec": (_F.Aztec,),
    "pdf417": (_F.PDF417,),
    "code128": (_F.Code128,),
    "code39": (_F.Code39,),
    "ean_upc": (_F.EAN13, _F.EAN8, _F.UPCA, _F.UPCE),
    "itf": (_F.ITF,),
    "databar": (_F.DataBar, _F.DataBarExp, _F.DataBarLtd),
}
"""The ``symbologies:`` names and the zxing-cpp formats each stands for."""

_MATRIX = {"datamatrix", "qr", "micro_qr", "aztec"}

_FORMAT_NAMES: dict[str, str] = {
    "DataMatrix": "datamatrix",
    "QRCode": "qr",
    "MicroQRCode": "micro_qr",
    "Aztec": "aztec",
    "PDF417": "pdf417",
    "Code128": "code128",
    "Code39": "code39",
    "EAN13": "ean_upc",
    "EAN8": "ean_upc",
    "UPCA": "ean_upc",
    "UPCE": "ean_upc",
    "ITF": "itf",
}

# fmt: off
_CONTROL_NAMES = [
    "NUL", "SOH", "STX", "ETX", "EOT", "ENQ", "ACK", "BEL", "BS", "HT", "LF", "VT", "FF", "CR",
    "SO", "SI", "DLE", "DC1", "DC2", "DC3", "DC4", "NAK", "SYN", "ETB", "CAN", "EM", "SUB",
    "ESC", "FS", "GS", "RS", "US",
]
# fmt: on


def human_readable(text: str) -> str:
    """``text`` with every ASCII control character spelled out: ``"A\\x1dB"`` -> ``"A<GS>B"``."""
    out = []
    for ch in text:
        code = ord(ch)
        if code < 0x20:
            out.append(f"<{_CONTROL_NAMES[code]}>")
        elif code == 0x7F:
            out.append("<DEL>")
        else:
            out.append(ch)
    return "".join(out)


@dataclass(frozen=True)
class Code:
    """One read code. ``text``: the payload as encoded (control characters kept);
    ``text_hri``: the same for people; ``symbology``: a :data:`SYMBOLOGIES` name; ``format``:
    zxing-cpp's own format name (e.g. ``EAN13``); ``corners`` (4, 2) float64 full-image pixels
    in symbol order; ``bbox`` ``(u, v, width, height)`` pixels; ``orientation_deg``: the
    symbol's rotation in the image as zxing-cpp reports it (degrees, clockwise on the screen);
    ``inverted``: light modules on a dark background; ``mirrored``: the symbol-order corners
    wind counter-clockwise on the screen (zxing-cpp reads a mirrored QR or DataMatrix by
    transposing its grid and reports clockwise corners for it, so those read as False);
    ``decoder``: which copy of the image read it (``zxing``, ``pyzbar``, ``zxing+sharpen``…)."""

    text: str
    text_hri: str
    symbology: str
    format: str
    corners: FloatArray
    bbox: tuple[float, float, float, float]
    orientation_deg: float
    inverted: bool
    mirrored: bool
    decoder: str
    grade: Grade


# --- escalation ----------------------------------------------------------------------------

Mapper = Callable[[FloatArray], FloatArray]


def _identity(p: FloatArray) -> FloatArray:
    return p


def _scaled(gray: GrayImage, f: float) -> tuple[GrayImage, Mapper]:
    interp = cv2.INTER_CUBIC if f > 1 else cv2.INTER_AREA
    img = np.asarray(cv2.resize(gray, None, fx=f, fy=f, interpolation=interp), np.uint8)
    s = np.array([img.shape[1] / gray.shape[1], img.shape[0] / gray.shape[0]])

    def back(p: FloatArray) -> FloatArray:
        out: FloatArray = (p + 0.5) / s - 0.5
        return out

    return img, back


def _padded(gray: GrayImage) -> tuple[GrayImage, Mapper]:
    pad = max(8, min(gray.shape) // 10)
    # the border takes the image's light level so that a symbol cut by the edge gets a quiet zone
    light = int(np.percentile(gray, 90))
    img = cv2.copyMakeBorder(gray, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=light)

    def back(p: FloatArray) -> FloatArray:
        out: FloatArray = p - pad
        return out

    return np.asarray(img, np.uint8), back


def _sharpened(gray: GrayImage) -> tuple[GrayImage, Mapper]:
    blurred = cv2.GaussianBlur(gray, (0, 0), 2.0)
    return np.asarray(cv2.addWeighted(gray, 2.0, blurred, -1.0, 0), np.uint8), _identity


def _smoothed(gray: GrayImage) -> tuple[GrayImage, Mapper]:
    return np.asarray(cv2.GaussianBlur(gray, (0, 0), 1.0), np.uint8), _identity


def _inverted_copy(gray: GrayImage) -> tuple[GrayImage, Mapper]:
    # zxing-cpp's own inversion retry covers matrix codes only; light-on-dark 1D codes and
    # PDF417 need the inverted image
    return np.asarray(255 - gray, np.uint8), _identity


def _plain(gray: GrayImage) -> tuple[GrayImage, Mapper]:
    return gray, _identity


def _resized(gray: GrayImage) -> tuple[GrayImage, Mapper]:
    # small symbols gain from more pixels per module, large photographs from less noise
    return _scaled(gray, 2.0 if min(gray.shape) < 600 else 0.5)


_LOCAL = zxingcpp.Binarizer.LocalAverage
_GLOBAL = zxingcpp.Binarizer.GlobalHistogram

Step = tuple[str, Callable[[GrayImage], tuple[GrayImage, Mapper]], zxingcpp.Binarizer]

ESCALATION: tuple[Step, ...] = (
    ("inverted", _inverted_copy, _LOCAL),
    ("histogram", _plain, _GLOBAL),
    ("resized", _resized, _LOCAL),
    ("sharpen", _sharpened, _LOCAL),
    ("smooth", _smoothed, _LOCAL),
    ("padded", _padded, _LOCAL),
)
"""The copies tried, in order, after the plain image read nothing: (label, make, binarizer)."""

DEBLUR_LENGTHS_PX: tuple[int, ...] = (3, 4, 5, 6, 8, 10)
"""Box motion-blur lengths (pixels) undone, along the rows then along the columns, for 1D
codes after every copy of :data:`ESCALATION` read nothing: about 25 % apart, as one length
restores a blur within roughly +/-20 % of it."""

_LINEAR = {
    _F.Code128,
    _F.Code39,
    _F.Code93,
    _F.Codabar,
    _F.EAN13,
    _F.EAN8,
    _F.UPCA,
    _F.UPCE,
    _F.ITF,
    _F.DataBar,
    _F.DataBarExp,
    _F.DataBarLtd,
}


def _transposed_back(p: FloatArray) -> FloatArray:
    out: FloatArray = p[..., ::-1].copy()
    return out


def _deblurred(
    gray: GrayImage, formats: Sequence[zxingcpp.BarcodeFormat]
) -> Iterator[tuple[str, GrayImage, Mapper]]:
    """The motion-blur copies (label, image, map back to ``gray``'s pixels), for 1D formats
    only: a matrix code's modules are blurred along both axes alike, and zxing-cpp's matrix
    readers gain nothing from them. Blur along the columns is undone on the transposed image,
    so that every copy has its bars across the rows and is read along the rows only."""
    if not any(f in _LINEAR for f in formats):
        return
    for image, along, back in ((gray, "rows", _identity), (gray.T, "columns", _transposed_back)):
        for length, img in deblur_axis(image, DEBLUR_LENGTHS_PX, axis=1):
            yield f"deblur_{along}_{length}px", img, back


@dataclass
class _Raw:
    text: str
    format: str
    quad: FloatArray  # (4, 2) pixels of the searched image, symbol order
    orientation_deg: float
    version: str | None
    decoder: str


def _formats(symbologies: Sequence[str]) -> list[zxingcpp.BarcodeFormat]:
    out: list[zxingcpp.BarcodeFormat] = []
    for name in symbologies:
        if name not in SYMBOLOGIES:
            raise ValueError(f"unknown symbology {name!r}; known: {', '.join(sorted(SYMBOLOGIES))}")
        out.extend(SYMBOLOGIES[name])
    if not out:
        raise ValueError("symbologies is empty: name at least one")
    return out


def _read(
    gray: GrayImage,
    formats: Sequence[zxingcpp.BarcodeFormat],
    binarizer: zxingcpp.Binarizer,
    *,
    along_rows: bool = False,
) -> list[_Raw]:
    """zxing-cpp's read; ``along_rows``: 1D codes with bars across the rows only, at full
    resolution (a deblurred copy: rotating or downscaling it costs time and gains nothing)."""
    out = []
    for b in zxingcpp.read_barcodes(
        gray,
        formats=zxingcpp.BarcodeFormats(list(formats)),
        text_mode=zxingcpp.TextMode.Plain,  # as encoded: control characters kept
        binarizer=binarizer,
        try_rotate=not along_rows,
        try_downscale=not along_rows,
    ):
        if not b.valid:
            continue
        pos = b.position
        quad = np.array(
            [
                [pos.top_left.x, pos.top_left.y],
                [pos.top_right.x, pos.top_right.y],
                [pos.bottom_right.x, pos.bottom_right.y],
                [pos.bottom_left.x, pos.bottom_left.y],
            ],
            dtype=np.float64,
        )
        extra = b.extra if isinstance(b.extra, dict) else {}
        version = extra.get("Version")
        out.append(
            _Raw(
                b.text,
                b.format.name,
                quad,
                float(b.orientation),
                None if version is None else str(version),
                "zxing",
            )
        )
    return out


def _pyzbar_qr(gray: GrayImage) -> list[_Raw]:
    out = []
    for d in pyzbar.decode(gray, symbols=[pyzbar.ZBarSymbol.QRCODE]):
        if len(d.polygon) != 4:
            continue
        quad = np.array([[p.x, p.y] for p in d.polygon], dtype=np.float64)
        # zbar's corners come in its own order: put them in the printed (symbol) order
        ordered, _ = order_corners(gray, quad)
        try:
            text = d.data.decode("utf-8")
        except UnicodeDecodeError:
            text = d.data.decode("latin-1")
        out.append(_Raw(text, "QRCode", ordered, 0.0, None, "pyzbar"))
    return out


def _escalate(
    gray: GrayImage, formats: Sequence[zxingcpp.BarcodeFormat], expect: Expect
) -> tuple[list[_Raw], list[str]]:
    """The plain read, then each :data:`ESCALATION` copy, the motion-blur copies and the
    reframed copies until one reads a matching code."""
    tried = ["zxing"]
    found = _read(gray, formats, _LOCAL)
    if any(matches(r.text, expect) for r in found):
        return found, tried
    if _F.QRCode in formats:
        # zbar reads some QR codes zxing-cpp misses (the qr inspection's union of decoders);
        # it runs only after zxing-cpp's plain read found nothing
        tried.append("pyzbar")
        found.extend(_pyzbar_qr(gray))
        if any(matches(r.text, expect) for r in found):
            return found, tried

    def attempt(
        label: str,
        img: GrayImage,
        back: Mapper,
        binarizer: zxingcpp.Binarizer,
        which: Sequence[zxingcpp.BarcodeFormat] = formats,
        *,
        along_rows: bool = False,
    ) -> bool:
        tried.append(f"zxing+{label}")
        new = _read(img, which, binarizer, along_rows=along_rows)
        for r in new:
            r.quad = back(r.quad)
            r.decoder = f"zxing+{label}"
        seen = {r.text for r in found}
        found.extend(r for r in new if r.text not in seen)
        return any(matches(r.text, expect) for r in new)

    for label, make, binarizer in ESCALATION:
        if attempt(label, *make(gray), binarizer):
            return found, tried
    linear = [f for f in formats if f in _LINEAR]
    for label, img, back in _deblurred(gray, linear):
        if attempt(label, img, back, _LOCAL, linear, along_rows=True):
            return found, tried
    for label, img, back in _reframed(gray):
        if attempt(label, img, back, _LOCAL):
            break
    return found, tried


_SIDES = ("left", "top", "right", "bottom")


def _reframed(gray: GrayImage) -> list[tuple[str, GrayImage, Mapper]]:
    """Copies for a symbol with no light quiet zone, set in a dark surround that merges with
    its dark edge modules (the finder L of a DataMatrix): the box of the light pixels, grown
    by one module on two adjacent sides (where the solid edge may lie: four choices), framed
    in light. Nothing when the image's border is not mostly dark."""
    _, binary = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    light = binary > 0
    frame = np.concatenate([light[0], light[-1], light[:, 0], light[:, -1]])
    if frame.mean() > 0.1 or not light.any():
        return []
    # the module: the 10th percentile of the light runs along the rows
    edges = np.diff(np.pad(light.astype(np.int8), ((0, 0), (1, 1))), axis=1)
    starts = np.flatnonzero(edges.reshape(-1) == 1)
    ends = np.flatnonzero(edges.reshape(-1) == -1)
    module = max(1, int(round(float(np.percentile(ends - starts, 10)))))
    rows = np.flatnonzero(light.any(axis=1))
    cols = np.flatnonzero(light.any(axis=0))
    box = {"top": rows[0], "bottom": rows[-1] + 1, "left": cols[0], "right": cols[-1] + 1}
    height, width = gray.shape
    pad = 4 * module
    level = int(np.median(gray[light]))  # the frame takes the symbol's own light level
    out: list[tuple[str, GrayImage, Mapper]] = []
    for k in range(4):
        grow = {_SIDES[k], _SIDES[(k + 1) % 4]}
        v0 = max(0, box["top"] - (module if "top" in grow else 0))
        v1 = min(height, box["bottom"] + (module if "bottom" in grow else 0))
        u0 = max(0, box["left"] - (module if "left" in grow else 0))
        u1 = min(width, box["right"] + (module if "right" in grow else 0))
        img = cv2.copyMakeBorder(
            gray[v0:v1, u0:u1], pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=level
        )
        shift = np.array([u0 - pad, v0 - pad], np.float64)

        def back(p: FloatArray, shift: FloatArray = shift) -> FloatArray:
            out_p: FloatArray = p + shift
            return out_p

        label = "reframed_" + "_".join(sorted(grow))
        out.append((label, np.asarray(img, np.uint8), back))
    return out


def _counter_clockwise(quad: FloatArray) -> bool:
    x, y = quad[:, 0], quad[:, 1]
    # v points down: a negative shoelace sum is counter-clockwise on the screen
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0


# --- the reader ----------------------------------------------------------------------------


def read_codes(
    image: NDArray[np.generic],
    *,
    symbologies: Sequence[str] = tuple(SYMBOLOGIES),
    roi: Sequence[int] | None = None,
    expect: Expect = None,
) -> list[Code]:
    """Read the codes of ``symbologies`` in ``image`` (uint8 grey or BGR; (u, v) pixels).

    ``roi`` ``[u, v, width, height]`` restricts the search; ``expect`` (an exact string, or a
    compiled pattern that must match the whole payload) selects codes and keeps escalating
    until one matches. Returns the codes in reading order (the first copy that read them,
    then zxing-cpp's order), corners in full-image pixels.

    Raises ValueError (unknown symbology), BadImageError, RoiError, or NotFoundError naming
    what was tried and, with ``expect``, what was read instead.
    """
    formats = _formats(symbologies)
    gray, offset = crop_for_code(
        gray_for_code(image, min_side=MIN_SIDE_PX, what="a code"),
        roi,
        min_side=MIN_SIDE_PX,
        what="a code",
    )
    found, tried = _escalate(gray, formats, expect)
    codes = []
    for r in found:
        if not matches(r.text, expect):
            continue
        # zxing-cpp names DataBar's variants (DataBarOmni, DataBarExp...) one by one
        default = "databar" if r.format.startswith("DataBar") else r.format.lower()
        symbology = _FORMAT_NAMES.get(r.format, default)
        quad = r.quad
        u0, v0 = quad.min(axis=0)
        u1, v1 = quad.max(axis=0)
        full = quad + offset
        codes.append(
            Code(
                text=r.text,
                text_hri=human_readable(r.text),
                symbology=symbology,
                format=r.format,
                corners=full,
                bbox=(float(u0 + offset[0]), float(v0 + offset[1]), float(u1 - u0), float(v1 - v0)),
                orientation_deg=r.orientation_deg,
                inverted=is_inverted(gray, quad),
                mirrored=symbology in _MATRIX and _counter_clockwise(quad),
                decoder=r.decoder,
                grade=grade_code(gray, quad, symbology, r.version),
            )
        )
    if not codes:
        names = ", ".join(symbologies)
        what = f"no code ({names})" if expect is None else f"no code matching {describe(expect)}"
        seen = [human_readable(r.text) for r in found]
        extra = f"; read instead: {seen}" if seen else ""
        raise NotFoundError(f"{what} found (tried {', '.join(tried)}){extra}")
    return codes
