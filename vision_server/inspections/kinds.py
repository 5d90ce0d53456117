"""What each inspection type's results hold, for readers that do not know the type.

Every type module declares one :class:`ResultKind` (``RESULTS``) beside its parser: the keys a
golden case's expected entry may check and how such an entry is made from a result's data
(:mod:`vision_server.commands.golden`), and the few numbers a reader with no room for JSON
takes from a result (:meth:`ResultKind.summary`: the registers a PLC reads over Modbus, the
fields of a line-protocol answer). Adding a type means adding its ``RESULTS``, not editing the
readers.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

Data = Mapping[str, Any]


@dataclass(frozen=True)
class ResultKind:
    """One inspection type's result shape.

    ``expected_keys``: what a golden case may expect of a result besides its verdict.
    ``expected``: a result's data as a golden expected entry (those keys, rounded; nothing for
    what was not found). ``summary``: named numbers, in a fixed order per type (missing values
    are NaN), e.g. ``{"count": 2.0, "u": 311.4, "v": 208.9}``. ``units``: the unit of each
    summary value that has one (``"px"``, ``"m"``), for the tables readers work from (the
    Modbus register map).
    """

    expected_keys: tuple[str, ...]
    expected: Callable[[Data], dict[str, Any]]
    summary: Callable[[Data], dict[str, float]]
    units: Mapping[str, str] = field(default_factory=dict)


def as_number(data: Data, key: str) -> float:
    """``data[key]`` as a float; NaN when it is absent or null."""
    value = data.get(key)
    return float("nan") if value is None else float(value)


def points(values: Any) -> list[list[float]]:
    """A list of [u, v] rounded to 0.01 px, as a golden case writes them."""
    return [[round(float(u), 2), round(float(v), 2)] for u, v in values]


__all__ = ["Data", "ResultKind", "as_number", "points"]
