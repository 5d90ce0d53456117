"""A RESULT for the command-line tools, the same in both: as JSON (:func:`result_json`), and its
``data`` as text for people (:func:`result_view`): scalar fields as
``name value`` lines, lists of features (or corners, or a matrix) as tables, numbers rounded to
what a person reads. Pure functions returning plain data; each tool draws it (``--json`` keeps
full precision).

Rounding and units, by field name (the last part of a dotted name):

==========================================  ===========================================
field                                       shown as
==========================================  ===========================================
``u``, ``v``, ``x``, ``y``, ``radius``,      pixels, 2 decimals
``width``, ``height``, ``*_px``
``score``, ``*_score``                      3 decimals
``angle``, ``*_rad``                        degrees, 1 decimal; the name says ``(deg)``
``*_m``                                     millimetres, 2 decimals; the name says ``(mm)``
``*_ms``                                    1 decimal
other numbers                               4 significant digits
==========================================  ===========================================
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from .messages import Result

__all__ = ["ResultView", "TableView", "format_number", "label", "result_json", "result_view"]

_PIXELS = frozenset({"u", "v", "x", "y", "radius", "width", "height"})
_FIRST = ("u", "v", "angle", "score")


@dataclass(frozen=True)
class TableView:
    """A list in the data: a title, column names (``show_header`` False for a bare matrix) and
    rows of text, one per item."""

    title: str
    columns: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    show_header: bool = True


@dataclass(frozen=True)
class ResultView:
    """``fields``: (label, text) of every scalar, nested objects flattened as ``a.b``;
    ``tables``: every list of objects or of number lists."""

    fields: tuple[tuple[str, str], ...] = ()
    tables: tuple[TableView, ...] = field(default_factory=tuple)


def label(name: str) -> str:
    """The name a field is shown under: its unit when the value is converted."""
    last = name.rsplit(".", 1)[-1]
    if last == "angle":
        return f"{name} (deg)"
    for suffix, unit in (("_rad", "deg"), ("_m", "mm")):
        if last.endswith(suffix):
            return f"{name[: -len(suffix)]} ({unit})"
    return name


def format_number(name: str, value: Any) -> str:
    """``value`` of the field ``name`` as text, rounded (and converted) by the module's table."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return _visible(value)
    if not isinstance(value, float):
        return str(value)
    if not math.isfinite(value):
        return str(value)
    return _unsigned_zero(_format_float(name.rsplit(".", 1)[-1], value))


def _unsigned_zero(text: str) -> str:
    """``-0.0`` (a value that rounds to zero from below) as ``0.0``: a person reads the sign
    as a direction that is not there."""
    if text.startswith("-") and not any(c in "123456789" for c in text.split("e")[0]):
        return text[1:]
    return text


def _format_float(last: str, value: float) -> str:
    if last in _PIXELS or last.endswith("_px"):
        return f"{value:.2f}"
    if last == "score" or last.endswith("_score"):
        return f"{value:.3f}"
    if last == "angle" or last.endswith("_rad"):
        return f"{math.degrees(value):.1f}"
    if last.endswith("_m"):
        return f"{value * 1000.0:.2f}"
    if last.endswith("_ms"):
        return f"{value:.1f}"
    return f"{value:.4g}" if abs(value) < 1e6 else f"{value:.0f}"


def _visible(text: str) -> str:
    """``text`` with its control characters written as escapes (``\\x1d``): a payload's GS
    or RS (GS1, ISO 15434) would otherwise move a terminal's cursor or vanish."""
    if text.isprintable():
        return text
    return "".join(ch if ch.isprintable() or ch == " " else f"\\x{ord(ch):02x}" for ch in text)


def result_json(result: Result, *, image: str | None) -> dict[str, Any]:
    """The one shape of a result on stdout with ``--json``, in both tools
    (docs/integrator-guide.md §6); full precision. ``image``: the file inspected, None when a
    server camera took the picture (a folder camera names its file in ``data.source_files``)."""
    return {
        "inspection": result.inspection,
        "verdict": "pass" if result.passed else "fail",
        "camera": result.camera,
        "image": image,
        "data": result.data,
        "timing": result.timing,
    }


def result_view(data: Mapping[str, Any]) -> ResultView:
    """The view of a RESULT's ``data`` (see the module)."""
    fields: list[tuple[str, str]] = []
    tables: list[TableView] = []
    _collect("", data, fields, tables)
    return ResultView(tuple(fields), tuple(tables))


def _collect(
    prefix: str, data: Mapping[str, Any], fields: list[tuple[str, str]], tables: list[TableView]
) -> None:
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            _collect(f"{name}.", value, fields, tables)
        elif isinstance(value, list | tuple):
            table = _table(name, value)
            if table is None:
                fields.append((name, ", ".join(format_number(name, v) for v in value) or "none"))
            else:
                tables.append(table)
        else:
            fields.append((label(name), format_number(name, value)))


def _table(name: str, items: Sequence[Any]) -> TableView | None:
    """A table for a non-empty list of objects or of number lists; None for anything else."""
    if not items:
        return None
    if all(isinstance(item, Mapping) for item in items):
        present = {k for item in items for k in item}
        # Position and quality first, whatever order the keys arrived in.
        columns = [k for k in _FIRST if k in present]
        for item in items:
            columns += [k for k in item if k not in columns]
        rows = tuple(
            (str(i), *(_cell(c, item.get(c)) for c in columns)) for i, item in enumerate(items, 1)
        )
        return TableView(name, ("#", *(label(c) for c in columns)), rows)
    if all(_numbers(item) for item in items):
        width = max(len(item) for item in items)
        if name.rsplit(".", 1)[-1] == "corners" and width == 2:  # [u, v] per corner c0..c3
            rows = tuple(
                (f"c{i}", *(format_number(axis, x) for axis, x in zip("uv", item, strict=False)))
                for i, item in enumerate(items)
            )
            return TableView(name, ("corner", "u", "v"), rows)
        rows = tuple(tuple(f"{x:.4f}" for x in item) for item in items)  # e.g. a 4x4 transform
        return TableView(name, ("",) * width, rows, show_header=False)
    return None


def _numbers(item: Any) -> bool:
    return (
        isinstance(item, list | tuple)
        and bool(item)
        and all(isinstance(x, int | float) and not isinstance(x, bool) for x in item)
    )


def _cell(name: str, value: Any) -> str:
    if isinstance(value, Mapping | list | tuple):
        return str(value)  # rare in a feature; shown whole rather than hidden
    return format_number(name, value)
