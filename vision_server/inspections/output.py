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

from ..configfile import Node, integer, number, string
from .kinds import ResultKind

MAX_FIELDS = 29
"""Values an answer carries besides the verdict: URScript's socket_read_ascii_float reads at
most 30 numbers, and the verdict is one of them."""
MAX_DECIMALS = 6
DEFAULT_DECIMALS = 3


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

    def values(self, summary: Mapping[str, float]) -> list[tuple[float, int]]:
        """``(value, decimals)`` of each field."""
        return [(f.value(summary, self.missing), f.decimals) for f in self.fields]


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


def parse_output(node: Node, kind: ResultKind | None, inspection_type: str) -> OutputFormat:
    """Read an inspection's ``output:`` mapping::

        output:
          fields: [count, u, {name: v, decimals: 1}]   # summary values, in this order
          decimals: 2                                   # the default for every field
          scale: {x: 1000}                              # e.g. metres -> millimetres
          missing: -1                                   # sent for a value not measured

    Raises ConfigError naming the key that is wrong (an unknown field names those there are).
    """
    available = summary_fields(kind)
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
        if name not in available:
            offered = ", ".join(available) or "none"
            raise field_node.error(
                f"{inspection_type} results have no summary value {name!r} (there are: {offered})",
                "name",
            )
        places = field_node.take("decimals", _decimals, decimals)
        field_scale = field_node.take("scale", _scale, scales.get(name, 1.0))
        field_node.finish()
        fields.append(OutputField(name, places, field_scale))
    for key in scales:
        if key not in {f.name for f in fields}:
            raise scale_node.error(f"{key!r} is not one of the output's fields", key)
    node.finish()
    return OutputFormat(tuple(fields), missing)


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
    "OutputField",
    "OutputFormat",
    "default_output",
    "numbers_by_position",
    "parse_output",
    "summary_fields",
]
