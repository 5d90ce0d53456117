"""Every key of every inspection type and job step type, for the console's editor.

One table, made from docs/configuration.md's, that says for each key what control fits it:
its kind (``number``, ``integer``, ``boolean``, ``enum``, ``string``, ``regex``,
``expression``, ``roi``, ``point``, ``file``, ``list``, ``symbologies``, ``mapping``), whether
it is required, its default, its inclusive bounds (``min_exclusive`` when the lower bound is
not itself allowed: "a number > 0"), a step, a unit, the values of an enum, when it applies
(``when``: sibling keys and the values they must have) and a line of documentation. A nested
mapping's keys are dotted (``circle.min_radius_px``).

The loader stays the authority: tests check the table against it (every key the loader
accepts is here, every enum value listed is accepted, every bound is refused one step beyond,
naming the key: tests/vision_server/test_inspection_schema.py), so that the two cannot drift
without a failing test. Served as ``GET /api/schema`` (docs/console.md).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

from ..analysis import DICTIONARIES as _DICTIONARIES
from ..analysis import MEASURES as _MEASURES
from ..analysis import POLARITIES
from ..analysis import SYMBOLOGIES as _SYMBOLOGIES
from ..inspections import CALIPER_KINDS as _CALIPER_KINDS
from ..inspections import INSPECTION_TYPES as _INSPECTION_TYPES
from ..inspections import STEP_TYPES as _STEP_TYPES

__all__ = ["COMMON_KEYS", "STEP_COMMON_KEYS", "inspection_schema"]

Key = dict[str, Any]

# The values the loader takes, from where the loader takes them (never a copy to keep in step).
MEASURES = tuple(_MEASURES)
SYMBOLOGIES = tuple(_SYMBOLOGIES)
DICTIONARIES = tuple(_DICTIONARIES)
CALIPER_POLARITIES = tuple(POLARITIES)
CALIPER_KINDS = tuple(_CALIPER_KINDS)
INSPECTION_TYPES = tuple(_INSPECTION_TYPES)
STEP_TYPES = tuple(_STEP_TYPES)


def key(
    name: str,
    kind: str,
    doc: str,
    *,
    required: bool = False,
    default: Any = None,
    min: float | None = None,  # noqa: A002 - the schema's own field names
    max: float | None = None,  # noqa: A002
    min_exclusive: bool = False,
    step: float | None = None,
    unit: str | None = None,
    values: Sequence[str] | None = None,
    when: dict[str, Any] | None = None,
    items: dict[str, Any] | None = None,
) -> Key:
    """One KEY of the schema (docs/console.md, "GET /api/schema")."""
    out: Key = {
        "key": name,
        "kind": kind,
        "required": required,
        "default": default,
        "min": min,
        "max": max,
        "step": step,
        "unit": unit,
        "values": None if values is None else list(values),
        "when": when,
        "doc": doc,
    }
    if min_exclusive:
        out["min_exclusive"] = True
    if items is not None:
        out["items"] = items
    return out


def _number(name: str, doc: str, **kw: Any) -> Key:
    return key(name, "number", doc, **kw)


def _positive(name: str, doc: str, **kw: Any) -> Key:
    return key(name, "number", doc, min=0, min_exclusive=True, **kw)


# ----------------------------------------------------------------------------- common

COMMON_KEYS: tuple[Key, ...] = (
    key("name", "string", "the name clients ask for (letters, digits, _ - .)", required=True),
    key("type", "enum", "what it does", required=True, values=INSPECTION_TYPES),
    key("camera", "enum", "a camera from cameras", required=True),
    key(
        "roi",
        "roi",
        "where to look: [u, v, width, height] inside the camera's declared image (not for "
        "caliper or job)",
        unit="px",
    ),
    key("frames", "integer", "frames a server camera captures per request", default=1, min=1),
    key("description", "string", "for people", default=""),
    key(
        "number",
        "integer",
        "what a line-protocol trigger may send instead of the name (default: its position)",
        min=1,
    ),
    key(
        "output",
        "mapping",
        "what a line-protocol answer carries after the verdict (fields, decimals, scale, "
        "missing, frame, plane_z_m, offset_m, tool_rpy)",
    ),
)
"""The keys every inspection has (``roi``: not a job's or a caliper's)."""

WITHOUT_COMMON: dict[str, tuple[str, ...]] = {"job": ("roi",), "caliper": ("roi",)}
"""Common keys a type does not take."""


# ----------------------------------------------------------------------------- by type


def _expect(doc: str) -> list[Key]:
    return [
        key("expect", "string", f"{doc}: the exact text (or give expect.regex)"),
        key("expect.regex", "regex", f"{doc}: a full match of this Python regular expression"),
    ]


def _locate(*, in_job: bool = False) -> list[Key]:
    template = {"method": "template"}
    circle = {"method": "circle"}
    blob = {"method": "blob"}
    keys = [
        key("method", "enum", "how features are found", required=True,
            values=("template", "circle", "blob")),
        key("min_count", "integer", "pass when at least this many are found", default=1, min=1),
        key("max_count", "integer", "report at most this many", default=10, min=1),
        _number("min_score", "weakest template feature reported: normalised correlation",
                default=0.7, min=-1, max=1, step=0.01, when=template),
        _number("min_score", "weakest circle reported: share of the outline's rays that found "
                "its edge", default=0.6, min=0, max=1, step=0.01, when=circle),
        _number("min_score", "weakest blob reported: its area", default=0, min=0, unit="px²",
                when=blob),
        key("template.image", "file", "the template image file (read as grey)", required=True,
            when=template),
        _number("template.angle_min", "rotation search from this angle", default=0, unit="rad",
                step=0.0175, when=template),
        _number("template.angle_max", "to this angle; at most a full turn beyond angle_min",
                default=0, unit="rad", step=0.0175, when=template),
        _positive("template.angle_step", "in steps of this", default=0.0175, unit="rad",
                  step=0.0025, when=template),
        _number("template.scale_min", "scale search (part size / template size) from this",
                default=1, min=0.5, max=2, step=0.01, when=template),
        _number("template.scale_max", "to this", default=1, min=0.5, max=2, step=0.01,
                when=template),
        _positive("template.scale_step", "in steps of this", default=0.02, step=0.01,
                  when=template),
        _positive("circle.min_radius_px", "smallest radius", required=True, unit="px", step=1,
                  when=circle),
        _positive("circle.max_radius_px", "largest radius", required=True, unit="px", step=1,
                  when=circle),
        key("circle.polarity", "enum", "a bright disc on a darker background, or the reverse",
            default="bright", values=("bright", "dark"), when=circle),
        key("circle.edge_sigma_px", "number", "the edges' blur as a Gaussian sigma, or 'auto' "
            "(measured on each candidate)", default="auto", min=0, min_exclusive=True,
            unit="px", step=0.1, when=circle),
        _positive("circle.max_edge_sigma_px", "a candidate blurred wider than this is rejected",
                  default=6, unit="px", step=0.1, when=circle),
        _positive("circle.min_edge_contrast", "smallest step across the edge for a ray to count",
                  default=15, max=255, unit="grey levels", step=1, when=circle),
        key("circle.rays", "integer", "radial rays cast from a candidate's centre", default=180,
            min=16, max=3600, when=circle),
        key("circle.centre", "enum", "the centre of the edge fit, or of the part's light",
            default="edge", values=("edge", "moments"), when=circle),
        key("blob.threshold", "number", "grey level separating blob from background, or 'otsu'",
            default="otsu", min=0, max=255, step=1, unit="grey level", when=blob),
        key("blob.polarity", "enum", "blobs darker or brighter than the threshold",
            default="dark", values=("dark", "bright"), when=blob),
        _positive("blob.min_area_px", "smallest blob area", default=20, unit="px²", when=blob),
        _positive("blob.max_area_px", "largest blob area; not below min_area_px", unit="px²",
                  when=blob),
        _number("blob.min_circularity", "4π·area/perimeter²; 1 for a disc", default=0, min=0,
                max=1, step=0.01, when=blob),
    ]  # fmt: skip
    keys.insert(
        keys.index(next(k for k in keys if k["key"] == "circle.centre")) + 1,
        key("circle.show_rejected", "boolean", "draw the rejected Hough candidates"
            + (" (not offered in a job's step: only false)" if in_job else ""),
            default=False, when=circle),
    )  # fmt: skip
    return keys


def _presence() -> list[Key]:
    thresholded = {"measure": ["dark_fraction", "bright_fraction", "blob_count"]}
    blobs = {"measure": ["blob_count"]}
    return [
        key("measure", "enum", "what is measured over the ROI", required=True, values=MEASURES),
        _number("min", "lowest passing value (give min, max or both), in the measure's range",
                step=0.01),
        _number("max", "highest passing value, in the measure's range", step=0.01),
        _number("threshold", "grey level (default: Otsu's on each image)", min=0, max=255,
                step=1, unit="grey level", when=thresholded),
        key("template", "file", "the template image for template_score", required=True,
            when={"measure": ["template_score"]}),
        key("min_blob_area", "integer", "smallest blob counted", default=20, min=0, unit="px²",
            when=blobs),
        key("polarity", "enum", "blobs darker or brighter than threshold", default="dark",
            values=("dark", "bright"), when=blobs),
    ]  # fmt: skip


PRESENCE_RANGES = {
    "mean_intensity": (0, 255),
    "dark_fraction": (0, 1),
    "bright_fraction": (0, 1),
    "edge_density": (0, 1),
    "blob_count": (0, None),
    "template_score": (-1, 1),
}
"""Each measure's range, which ``min`` and ``max`` must lie in (served as ``ranges``)."""


def _anomaly() -> list[Key]:
    return [
        key("model", "file", "the model file vision-server train (or the console's Train) "
            "wrote; none: not trained yet"),
        _number("threshold", "a score above it fails (default: the model's own)", min=0,
                step=0.01),
        key("method", "enum", "how training models the good parts", default="patches",
            values=("patches", "variation")),
        _number("false_reject", "the share of good parts training's threshold may fail",
                min=0, max=0.5, min_exclusive=True, step=0.005),
    ]  # fmt: skip


def _code() -> list[Key]:
    return [
        key("symbologies", "symbologies", "what to look for (default: all of them)",
            values=SYMBOLOGIES),
        *_expect("the payload wanted, as encoded"),
        _number("min_grade.module_px", "lowest module size that passes", min=0, unit="px",
                step=0.1),
        _number("min_grade.contrast", "lowest symbol contrast that passes", min=0, step=0.01),
        _number("min_grade.decode_margin", "lowest decode margin that passes", min=0, step=0.01),
        _number("min_grade.quiet_zone_modules", "narrowest quiet zone that passes", min=0,
                unit="modules", step=0.5),
    ]  # fmt: skip


def _qr() -> list[Key]:
    return [
        *_expect("the text wanted"),
        key("corners", "enum", "corners refined to a fraction of a pixel, or the decoder's",
            default="subpixel", values=("subpixel", "decoder")),
    ]  # fmt: skip


def _qr_pose() -> list[Key]:
    return [
        key("method", "enum", "a plane fitted to the code's depth, or the mean depth at each "
            "corner", default="plane", values=("plane", "corners")),
        *_expect("the code's text"),
        _positive("side_m", "the printed side length of the code", unit="m", step=0.001),
        _positive("max_plane_rms_m", "fail when the plane's RMS residual is larger", unit="m",
                  step=0.0005),
        _number("min_valid_fraction", "fail when fewer pixels of the code have depth", min=0,
                max=1, step=0.01),
        _positive("depth_scale", "the depth sensor reads this times the true distance",
                  default=1, step=0.001),
        key("depth_shift_px", "point", "depth pixel (u, v) saw colour pixel (u - du, v - dv)",
            default=[0, 0], unit="px"),
        _number("depth_scale_std", "the sensor check's standard error of depth_scale", min=0,
                step=0.001),
        key("depth_shift_std_px", "point", "the sensor check's standard errors of "
            "depth_shift_px", default=[0, 0], min=0, unit="px"),
        _number("corner_bias_px", "how much too long the corner detector reads the code's side",
                min=-1, max=1, unit="px", step=0.01),
        _number("unchecked_scale_std", "depth scale error assumed of an unchecked sensor",
                default=0.01, min=0, max=0.2, step=0.001),
        _number("unchecked_shift_std_px", "depth-to-colour misregistration assumed of an "
                "unchecked sensor", default=2, min=0, max=50, unit="px", step=0.1),
        _positive("max_depth_vs_side", "warn when the depth and the printed side disagree by "
                  "more (relative)", default=0.003, step=0.001),
    ]  # fmt: skip


def _measurement_keys() -> list[Key]:
    banded = {"kind": ["edge", "width", "line"]}
    circle = {"kind": ["circle"]}
    return [
        key("name", "string", "unique in the inspection", required=True),
        key("kind", "enum", "edge, width (an edge pair), circle, line or distance",
            required=True, values=CALIPER_KINDS),
        key("band.center", "point", "the band's centre", required=True, unit="px", when=banded),
        _number("band.length", "along the scan", required=True, min=3, unit="px", step=1,
                when=banded),
        _number("band.width", "across the scan (the profile is the mean across it)", default=1,
                min=1, unit="px", step=1, when=banded),
        _number("band.angle_rad", "the scan's direction from +u towards +v", default=0,
                unit="rad", step=0.0175, when=banded),
        key("polarity", "enum", "which way the grey level steps along the scan",
            default="any", values=CALIPER_POLARITIES, when={"kind": ["edge", "line", "circle"]}),
        key("select", "enum", "which edge (pair) along the scan is taken", default="strongest",
            values=("first", "last", "strongest"),
            when={"kind": ["edge", "width", "line", "circle"]}),
        key("first", "enum", "the pair's first edge", default="dark_to_light",
            values=CALIPER_POLARITIES, when={"kind": ["width"]}),
        key("second", "enum", "the pair's second edge", default="light_to_dark",
            values=CALIPER_POLARITIES, when={"kind": ["width"]}),
        _positive("expected", "the width looked for: the closest pair is taken",
                  when={"kind": ["width"]}),
        _positive("tolerance", "only pairs this close to expected count",
                  when={"kind": ["width"]}),
        _positive("min_strength", "the weakest edge (slope of the profile)", default=5,
                  unit="grey levels/px", step=1,
                  when={"kind": ["edge", "width", "line", "circle"]}),
        _number("smoothing", "sigma of the Gaussian derivative along the scan", default=1,
                min=0.3, max=20, unit="px", step=0.1,
                when={"kind": ["edge", "width", "line", "circle"]}),
        key("center", "point", "the circle's expected centre", required=True, unit="px",
            when=circle),
        _positive("radius", "its expected radius", required=True, unit="px", step=1,
                  when=circle),
        _positive("search", "how far either side of radius each radial scan looks",
                  default=10, unit="px", step=1, when=circle),
        key("rays", "integer", "radial scans; half of them must find the edge", default=32,
            min=3, max=720, when=circle),
        _positive("band_width", "width of each radial scan", default=3, unit="px", step=1,
                  when=circle),
        key("arc_rad", "point", "the arc scanned [from, to], radians from +u towards +v",
            default=[0, 6.2832], unit="rad", when=circle),
        key("segments", "integer", "strips across the band, one edge point each", default=8,
            min=2, when={"kind": ["line"]}),
        key("from", "string", "an earlier measurement", required=True,
            when={"kind": ["distance"]}),
        key("to", "string", "an earlier line", required=True, when={"kind": ["distance"]}),
        key("value", "enum", "diameter or roundness", default="diameter",
            values=("diameter", "roundness"), when=circle),
        key("value", "enum", "signed distance, or angle between two lines",
            default="distance", values=("distance", "angle"), when={"kind": ["distance"]}),
        _number("min", "the tolerance's low end (in the unit)", step=0.01),
        _number("max", "the tolerance's high end (in the unit)", step=0.01),
    ]  # fmt: skip


def _caliper_units() -> list[Key]:
    mm = {"units": ["mm"]}
    return [
        key("units", "enum", "the unit of every length", default="px", values=("px", "mm")),
        _positive("plane_distance_m", "mm through the camera's intrinsics: the plane this far "
                  "from the camera (give it or mm_per_px)", unit="m", step=0.001, when=mm),
        _positive("mm_per_px", "mm through a scale from a reference of known size", step=0.001,
                  when=mm),
    ]  # fmt: skip


def _caliper() -> list[Key]:
    return [
        *_caliper_units(),
        key("measurements", "list", "at least one, run in order", required=True,
            items={"keys": _measurement_keys()}),
    ]  # fmt: skip


def _calibration_board() -> list[Key]:
    charuco = {"board.kind": ["charuco"]}
    return [
        key("board.kind", "enum", "the pattern", required=True,
            values=("charuco", "chessboard")),
        key("board.columns", "integer", "squares across", required=True, min=3),
        key("board.rows", "integer", "squares down", required=True, min=3),
        _positive("board.square_m", "the side of a square", required=True, unit="m",
                  step=0.001),
        _positive("board.marker_m", "the side of a marker, less than square_m", required=True,
                  unit="m", step=0.001, when=charuco),
        key("board.dictionary", "enum", "the markers' dictionary", default="DICT_4X4_50",
            values=DICTIONARIES, when=charuco),
        key("min_corners", "integer", "corners needed for a pass", default=6, min=1),
    ]  # fmt: skip


def _job() -> list[Key]:
    return [
        key("steps", "list", "the steps, in the order they run (1..32; their keys under "
            "the schema's steps)", required=True),
        key("verdict", "expression", "the expression that decides pass or fail (default: "
            "every step passes)"),
    ]  # fmt: skip


TYPE_DOCS = {
    "locate": "feature locate: sub-pixel (u, v) of features, best first; passes when at "
    "least min_count are found",
    "presence": "one measure over the ROI; passes when it lies in [min, max]",
    "qr": "reads QR codes: the text and the four corners",
    "code": "reads a 2D or 1D code: payload, corners and grade",
    "qr_pose": "the pose camera_from_qr of a QR code from colour and depth frames",
    "caliper": "measurements with tolerances: edges, widths, circles, lines, distances",
    "calibration_board": "the inner corners of a ChArUco board or chessboard",
    "job": "named steps run in order (locate, fixture, presence, code, caliper, anomaly) and "
    "a verdict",
    "anomaly": "a score of how unlike the good parts it was trained on the ROI is, and a heat "
    "map; passes when the score is at most the threshold",
}


# ----------------------------------------------------------------------------- steps

STEP_COMMON_KEYS: tuple[Key, ...] = (
    key("name", "string", "an identifier: what later steps and the verdict call it",
        required=True),
    key("type", "enum", "what the step does", required=True, values=STEP_TYPES),
    key("fixture", "string", "a fixture step before this one: the part frame this step's roi "
        "is given in"),
    key("roi", "roi", "image pixels; with fixture: required, in the part frame's pixels (x, y "
        "may be negative); a fixture or caliper step has none", unit="px"),
)  # fmt: skip
"""The keys every job step has."""

STEP_WITHOUT_COMMON: dict[str, tuple[str, ...]] = {
    "fixture": ("fixture", "roi"),
    "caliper": ("roi",),
}


def _fixture_step() -> list[Key]:
    return [
        key("origin", "string", "a locate step: the frame's origin is its first feature",
            required=True),
        key("x_towards", "string", "a locate step: the x axis points to its first feature"),
        key("angle_from", "string", "a template or blob locate step: the x axis at its "
            "feature's angle (not with x_towards)"),
    ]  # fmt: skip


STEP_DOCS = {
    "locate": "a locate's keys; passes when count >= min_count",
    "fixture": "a part frame from a locate step's feature",
    "presence": "a presence check's keys over the step's ROI",
    "code": "a code read's keys in the step's ROI",
    "caliper": "a caliper's keys; in a fixture's frame the geometry is in the part frame",
    "anomaly": "an anomaly check's keys over the step's ROI (in a fixture's frame: aligned)",
}


# ----------------------------------------------------------------------------- sections


def _mqtt_section() -> list[Key]:
    """``mqtt:`` (docs/configuration.md, "mqtt"; the loader: cell.py ``_mqtt``)."""
    return [
        key("enabled", "boolean", "publish results to an MQTT broker", default=False),
        key("host", "string", "the broker's host name or address", default="127.0.0.1"),
        key("port", "integer", "the broker's port (8883 with tls)", default=1883, min=1, max=65535),
        key("cell", "string", "this cell's topic level (default: server.name)"),
        key(
            "topic_prefix", "string", "the first topic level(s), /-separated", default="cellvision"
        ),
        key("client_id", "string", "the MQTT client identifier (default: cellvision-<cell>)"),
        key("username", "string", "sign in with this name"),
        key("password", "string", "... and this password (or password_file, password_env)"),
        key("password_file", "file", "the password read from this file"),
        key("password_env", "string", "the password read from this environment variable"),
        key("tls.ca", "file", "the CA (PEM) the broker's certificate is checked against"),
        key("tls.cert", "file", "a client certificate (PEM), with tls.key"),
        key("tls.key", "file", "the client certificate's private key (PEM)"),
        key("keepalive_s", "integer", "MQTT keep-alive", default=30, min=1, max=65535, unit="s"),
        key(
            "max_in_flight",
            "integer",
            "results unacknowledged at once",
            default=64,
            min=1,
            max=65535,
        ),
        key("spool", "string", "the spool's SQLite file (default: mqtt-spool.sqlite beside it)"),
        _positive("spool_max_mb", "the spool's bound; past it the oldest are dropped", default=100),
        _positive("reconnect_min_s", "first wait before reconnecting", default=0.5, unit="s"),
        _positive("reconnect_max_s", "longest wait between reconnects", default=30, unit="s"),
        _positive(
            "publish_timeout_s", "a PUBACK this late ends the connection", default=30, unit="s"
        ),
    ]


SECTION_DOCS = {
    "mqtt": "every production result published to an MQTT broker (docs/mqtt.md)",
}


# ----------------------------------------------------------------------------- the whole


def inspection_schema(cameras: Sequence[str] | None = None) -> dict[str, Any]:
    """The schema served as ``GET /api/schema``: ``types``, ``steps``, ``common`` (and
    ``step_common``, ``presence_ranges``, and ``sections``: the keys of configuration sections
    besides the inspections that it describes, so far ``mqtt``). ``cameras``: the configured
    cameras' names, which ``camera`` takes (None: not listed)."""
    common = copy.deepcopy(list(COMMON_KEYS))
    if cameras is not None:
        next(k for k in common if k["key"] == "camera")["values"] = list(cameras)
    by_type = {
        "locate": _locate(),
        "presence": _presence(),
        "qr": _qr(),
        "code": _code(),
        "qr_pose": _qr_pose(),
        "caliper": _caliper(),
        "calibration_board": _calibration_board(),
        "job": _job(),
        "anomaly": _anomaly(),
    }
    types = {
        name: {
            "doc": TYPE_DOCS[name],
            "keys": keys,
            "without_common": list(WITHOUT_COMMON.get(name, ())),
            **({"default_frames": 5} if name == "qr_pose" else {}),
        }
        for name, keys in by_type.items()
    }
    by_step = {
        "locate": _locate(in_job=True),
        "fixture": _fixture_step(),
        "presence": _presence(),
        "code": _code(),
        "caliper": _caliper(),
        "anomaly": _anomaly(),
    }
    steps = {
        name: {
            "doc": STEP_DOCS[name],
            "keys": [
                *(
                    copy.deepcopy(k)
                    for k in STEP_COMMON_KEYS
                    if k["key"] not in STEP_WITHOUT_COMMON.get(name, ())
                ),
                *keys,
            ],
        }
        for name, keys in by_step.items()
    }
    return {
        "types": types,
        "steps": steps,
        "common": common,
        "step_common": copy.deepcopy(list(STEP_COMMON_KEYS)),
        "presence_ranges": {m: list(r) for m, r in PRESENCE_RANGES.items()},
        "sections": {"mqtt": {"doc": SECTION_DOCS["mqtt"], "keys": _mqtt_section()}},
    }
