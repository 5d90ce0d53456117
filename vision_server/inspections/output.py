"""What a narrow reader (a robot controller on the line protocol) gets of an inspection's
result: its number, and which summary values in which order, scaled and rounded how.

An inspection's ``number:`` and ``output:`` keys (docs/configuration.md) are read here. The
values come from the summary its type declares (:meth:`ResultKind.summary`), so nothing about
what an inspection measures is repeated: ``output:`` only picks, orders, scales and rounds.
Numbers are rendered by :mod:`vision_server.frontends.line`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from yamlfile import Node, integer, number, one_of, string

from ..cameras import CameraSettings, SimCameraSettings
from .base_frame import BaseFrame
from .kinds import ResultKind

MAX_FIELDS = 29
"""Values an answer carries besides the verdict: URScript's socket_read_ascii_float reads at
most 30 numbers, and the verdict is one of them."""
MAX_DECIMALS = 6
DEFAULT_DECIMALS = 3
POSE = "pose"
"""The field that stands for a base-frame pose (``output: {frame: base}``): x, y, z and the
rotation, in the answer format's convention (protocol/LINE.md §5.7)."""
MAX_POSE_NUMBERS = 7
"""The most numbers a pose is written with (ABB: x, y, z and a quaternion)."""
PIXELS = ("u", "v")
"""The summary values a base-frame pose is computed from (and replaces)."""


@dataclass(frozen=True)
class OutputField:
    """One value of an answer: summary value ``name`` times ``scale`` (e.g. 1000 for metres
    to millimetres), rounded to ``decimals`` places."""

    name: str
    decimals: int = DEFAULT_DECIMALS
    scale: float = 1.0

    def value(self, summary: Mapping[str, float], missing: float) -> float:
        """The scaled value; ``missing`` when the summary has NaN (nothing found) or none."""
        raw = summary.get(self.name, math.nan)
        if not math.isfinite(raw):
            return missing
        return raw * self.scale


@dataclass(frozen=True)
class OutputFormat:
    """The values of an answer after the verdict, in order. ``missing``: what a value that
    was not measured (NaN in the summary) is sent as, since controllers cannot parse NaN."""

    fields: tuple[OutputField, ...]
    missing: float = 0.0
    base: BaseFrame | None = None
    """How the ``pose`` field is computed (``frame: base``); None: positions in pixels."""

    def count(self, pose_count: int) -> int:
        """Numbers after the verdict when a pose is written with ``pose_count`` numbers."""
        return sum(pose_count if f.name == POSE else 1 for f in self.fields)

    def values(
        self, summary: Mapping[str, float], pose: Iterable[tuple[float, int]] | None = None
    ) -> list[tuple[float, int]]:
        """``(value, decimals)`` of each field; the ``pose`` field is ``pose``'s values
        (each ``missing`` when a value is not finite)."""
        out: list[tuple[float, int]] = []
        for f in self.fields:
            if f.name == POSE:
                for value, places in pose or ():
                    out.append((value if math.isfinite(value) else self.missing, places))
            else:
                out.append((f.value(summary, self.missing), f.decimals))
        return [(_rounded(value, places), places) for value, places in out]


def _rounded(value: float, places: int) -> float:
    """``value`` to ``places`` decimals, a negative zero made positive: a controller that
    prints it or compares its sign bit must not see ``-0.000`` for an angle of zero."""
    return round(value, places) + 0.0


def summary_fields(kind: ResultKind | None) -> tuple[str, ...]:
    """The names of the values a type's summary holds, in its order (none for a type that
    declares no summary)."""
    return () if kind is None else tuple(kind.summary({}))


def default_output(kind: ResultKind | None) -> OutputFormat:
    """Every summary value of the type, in its order, with the default decimals."""
    return OutputFormat(tuple(OutputField(name) for name in summary_fields(kind)[:MAX_FIELDS]))


def _decimals(value: Any) -> int:
    places = integer(value)
    if not 0 <= places <= MAX_DECIMALS:
        raise ValueError(f"expected decimals in 0..{MAX_DECIMALS}, got {places}")
    return places


def _scale(value: Any) -> float:
    factor = number(value)
    if not math.isfinite(factor) or factor == 0.0:
        raise ValueError(f"expected a finite, non-zero scale, got {value!r}")
    return factor


def _field_list(value: Any) -> list[Any]:
    if not isinstance(value, list):
        raise ValueError(f"expected a list of summary values, got {type(value).__name__}")
    return value


def _triple(value: Any) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        raise ValueError(f"expected a list of 3 numbers, got {value!r}")
    x, y, z = (number(v) for v in value)
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise ValueError(f"expected finite numbers, got {value!r}")
    return x, y, z


def _base_frame(
    node: Node, available: tuple[str, ...], camera: str, settings: CameraSettings | None
) -> BaseFrame:
    """The keys of ``frame: base``, checked against the camera's calibration."""
    if not all(p in available for p in PIXELS):
        raise node.error(
            "frame: base needs a result with a pixel position (u, v), as locate's", "frame"
        )
    if settings is None:
        raise node.error(f"no camera named {camera!r}", "frame")
    intrinsics = getattr(settings, "intrinsics", None)
    mount = getattr(settings, "mount", None)
    # A sim camera without intrinsics has its scene camera's (known once the scene is loaded).
    has_intrinsics = intrinsics is not None or isinstance(settings, SimCameraSettings)
    lacking = [k for k, ok in (("intrinsics", has_intrinsics), ("mount", mount)) if not ok]
    if lacking or mount is None:
        raise node.error(
            f"frame: base needs the calibration of camera {camera!r}, which has no "
            f"{' and no '.join(lacking)}: set "
            + " and ".join(f"cameras.{camera}.{key}" for key in lacking),
            "frame",
        )
    plane_z = node.take("plane_z_m", number)
    offset = node.take("offset_m", _triple, (0.0, 0.0, 0.0))
    rpy = node.take("tool_rpy", _triple, (math.pi, 0.0, 0.0))
    return BaseFrame(camera, intrinsics, mount, plane_z, offset, rpy)


def parse_output(
    node: Node,
    kind: ResultKind | None,
    inspection_type: str,
    *,
    camera: str = "",
    settings: CameraSettings | None = None,
    extra: Mapping[str, str | None] | None = None,
) -> OutputFormat:
    """Read an inspection's ``output:`` mapping::

        output:
          fields: [count, u, {name: v, decimals: 1}]   # summary values, in this order
          decimals: 2                                   # the default for every field
          scale: {x: 1000}                              # e.g. metres -> millimetres
          missing: -1                                   # sent for a value not measured
          frame: base         # image (default) | base: u, v become a base-frame "pose"
          plane_z_m: 0.02     # with frame: base, the features' height in the base frame

    ``camera``/``settings``: the inspection's camera, whose calibration (``intrinsics``,
    ``mount``) ``frame: base`` needs. ``extra``: the summary values this inspection has
    besides its type's (a job's ``STEP.VALUE``), mapped to None, or to why it cannot be sent.
    Raises ConfigError naming the key that is wrong (an
    unknown field names those there are).
    """
    available = summary_fields(kind)
    base: BaseFrame | None = None
    if node.take("frame", one_of("image", "base"), "image") == "base":
        base = _base_frame(node, available, camera, settings)
        available = (*(a for a in available if a not in PIXELS), POSE)
    decimals = node.take("decimals", _decimals, DEFAULT_DECIMALS)
    missing = node.take("missing", number, 0.0)
    scales: dict[str, float] = {}
    scale_node = node.sub("scale")
    for key in list(scale_node.data):
        scales[str(key)] = scale_node.take(str(key), _scale)
    raw = node.take("fields", _field_list, list(available))
    if len(raw) > MAX_FIELDS:
        raise node.error(
            f"{len(raw)} fields; at most {MAX_FIELDS} (URScript reads 30 numbers, the "
            "verdict is the first)",
            "fields",
        )
    # A field is a name or a mapping {name, decimals, scale}: read both as mappings.
    node.data = {**node.data, "fields": [{"name": i} if isinstance(i, str) else i for i in raw]}
    fields: list[OutputField] = []
    for field_node in node.items("fields"):
        name = field_node.take("name", string)
        why_not = (extra or {}).get(name, "")
        if why_not:
            raise field_node.error(f"{name!r} cannot be sent: {why_not}", "name")
        if name not in available and name not in (extra or {}):
            own = [key for key, why in (extra or {}).items() if why is None]
            offered = ", ".join((*available, *own)) or "none"
            raise field_node.error(
                f"{inspection_type} results have no summary value {name!r} (there are: {offered})",
                "name",
            )
        if name == POSE:  # its units and decimals are the answer format's
            field_node.finish()
            fields.append(OutputField(name))
            continue
        places = field_node.take("decimals", _decimals, decimals)
        field_scale = field_node.take("scale", _scale, scales.get(name, 1.0))
        field_node.finish()
        fields.append(OutputField(name, places, field_scale))
    for key in scales:
        if key not in {f.name for f in fields}:
            raise scale_node.error(f"{key!r} is not one of the output's fields", key)
    node.finish()
    output = OutputFormat(tuple(fields), missing, base)
    widest = output.count(MAX_POSE_NUMBERS)
    if widest > MAX_FIELDS:
        raise node.error(
            f"{widest} numbers with a pose of 7 (ABB's quaternion); at most {MAX_FIELDS}",
            "fields",
        )
    return output


def numbers_by_position(
    declared: Iterable[tuple[str, int | None]],
) -> dict[int, str]:
    """Each inspection's number: its ``number:``, else its 1-based position in the list.
    ``declared``: ``(name, number or None)`` in configuration order. Raises ValueError naming
    both inspections when two end up with one number."""
    out: dict[int, str] = {}
    for position, (name, declared_number) in enumerate(declared, start=1):
        chosen = position if declared_number is None else declared_number
        if chosen in out:
            how = "its number:" if declared_number is not None else "its position in the list"
            raise ValueError(
                f"inspection {name!r} gets number {chosen} ({how}), which inspection "
                f"{out[chosen]!r} already has; give each a distinct number:"
            )
        out[chosen] = name
    return out


__all__ = [
    "MAX_FIELDS",
    "POSE",
    "OutputField",
    "OutputFormat",
    "default_output",
    "numbers_by_position",
    "parse_output",
    "summary_fields",
]
