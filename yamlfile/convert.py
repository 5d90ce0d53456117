"""Converters for ``Node.take``: each checks one plain YAML value and returns it typed, or
raises ValueError saying what was expected and what came (the node adds file, line and key)."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import Any

__all__ = [
    "NAME",
    "boolean",
    "fraction",
    "integer",
    "kind",
    "name",
    "non_negative",
    "non_negative_int",
    "number",
    "numbers",
    "one_of",
    "positive",
    "positive_int",
    "string",
]

NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
"""A name the files give things (cameras, inspections): safe in a path, a log line, a URL."""


def kind(value: Any) -> str:
    """How a value is shown in an error: ``nothing``, ``a mapping``, ``a list`` or its repr."""
    if value is None:
        return "nothing"
    return {dict: "a mapping", list: "a list", str: f"{value!r}", bool: f"{value!r}"}.get(
        type(value), f"{value!r}"
    )


# ----------------------------------------------------------------------------- converters
# Each raises ValueError with a message that says what was expected and what came.


def number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {kind(value)}")
    try:
        out = float(value)
    except OverflowError:  # an integer of hundreds of digits: no float holds it
        bits = int(value).bit_length()
        raise ValueError(f"expected a finite number, got an integer of {bits} bits") from None
    if not math.isfinite(out):
        raise ValueError(f"expected a finite number, got {value!r}")
    return out


def positive(value: Any) -> float:
    out = number(value)
    if out <= 0:
        raise ValueError(f"expected a number > 0, got {value!r}")
    return out


def non_negative(value: Any) -> float:
    out = number(value)
    if out < 0:
        raise ValueError(f"expected a number >= 0, got {value!r}")
    return out


def fraction(value: Any) -> float:
    out = number(value)
    if not 0.0 <= out <= 1.0:
        raise ValueError(f"expected a number in [0, 1], got {value!r}")
    return out


def integer(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"expected an integer, got {kind(value)}")
    return value


def positive_int(value: Any) -> int:
    out = integer(value)
    if out <= 0:
        raise ValueError(f"expected an integer > 0, got {value!r}")
    return out


def non_negative_int(value: Any) -> int:
    out = integer(value)
    if out < 0:
        raise ValueError(f"expected an integer >= 0, got {value!r}")
    return out


def boolean(value: Any) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"expected true or false, got {kind(value)}")
    return value


def string(value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"expected a non-empty string, got {kind(value)}")
    return value


def name(value: Any) -> str:
    out = string(value)
    if not NAME.fullmatch(out):
        raise ValueError(f"bad name {out!r}: use letters, digits, '_', '-' and '.' (max 64)")
    return out


def one_of(*choices: str) -> Callable[[Any], str]:
    def convert(value: Any) -> str:
        if value not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}; got {kind(value)}")
        return str(value)

    return convert


def numbers(
    count: int | None = None, *, each: Callable[[Any], float] = number
) -> Callable[[Any], tuple[float, ...]]:
    def convert(value: Any) -> tuple[float, ...]:
        if not isinstance(value, list) or (count is not None and len(value) != count):
            want = f"a list of {count} numbers" if count is not None else "a list of numbers"
            raise ValueError(f"expected {want}, got {kind(value)}")
        return tuple(each(v) for v in value)

    return convert
