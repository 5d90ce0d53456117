"""The line protocol's words (protocol/LINE.md), without I/O: a request line into a
:class:`Command`, answers into bytes.

Every failure is a :class:`protocol.CellvisionError` whose code is the number an error line
carries (LINE.md §6), so the table from causes to codes is the binary protocol's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from protocol import CellvisionError, InvalidArgument, MalformedFrame, UnknownMessageType

from .line_formats import WRITERS

EOL = b"\r\n"
"""What every answer ends with (a controller reading up to LF or CR LF takes both)."""
MAX_ERROR_TEXT = 160
"""Characters of an error line's message: enough to name the cause, short for a pendant."""

ARITY: dict[str, tuple[int, int]] = {
    "T": (1, 8),  # trigger <number|name> [the robot's TCP pose: 6 or 7 numbers]
    "R": (0, 1),  # last result (this connection's, or an inspection's)
    "L": (0, 0),  # list inspections
    "P": (0, 0),  # ping
    "A": (1, 1),  # authenticate <token>
    "F": (1, 1),  # answer format <text|ur|abb|kuka|fanuc>
    "Q": (0, 0),  # quit
}
"""Each command letter and how many arguments it takes (min, max)."""


@dataclass(frozen=True)
class Command:
    """One request line: its command letter (upper case) and its arguments."""

    verb: str
    args: tuple[str, ...] = ()

    @property
    def arg(self) -> str | None:
        return self.args[0] if self.args else None


def parse_line(raw: bytes) -> Command | None:
    """The command of one line (without its LF; a CR before it is dropped); None for a blank
    line. Raises MALFORMED_FRAME (1) for bytes that are not printable ASCII, UNKNOWN_MESSAGE_TYPE
    (4) for an unknown command letter, INVALID_ARGUMENT (16) for a wrong number of arguments."""
    line = raw[:-1] if raw.endswith(b"\r") else raw
    for index, byte in enumerate(line):
        if not (32 <= byte < 127 or byte == 9):
            raise MalformedFrame(
                f"byte {index} of the line is 0x{byte:02x}: lines are printable ASCII"
            )
    words = line.decode("ascii").split()
    if not words:
        return None
    verb = words[0].upper()
    if verb not in ARITY:
        raise UnknownMessageType(
            f"unknown command {_shown(words[0])!r}; commands: {' '.join(ARITY)}"
        )
    low, high = ARITY[verb]
    args = tuple(words[1:])
    if not low <= len(args) <= high:
        wanted = str(low) if low == high else f"{low} to {high}"
        raise InvalidArgument(f"{verb} takes {wanted} argument(s), got {len(args)}")
    return Command(verb, args)


def _shown(text: str) -> str:
    return text if len(text) <= 20 else text[:20] + "..."


def number_text(value: float, decimals: int) -> str:
    """``value`` in fixed-point with ``decimals`` places, never ``-0.00``, never NaN (a value
    that is not finite is the caller's to replace)."""
    if not math.isfinite(value):
        raise ValueError(f"not a finite number: {value}")
    text = f"{value:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0.0 else text


def ok_line(*words: str) -> bytes:
    return ("OK" + "".join(" " + w for w in words)).encode("ascii") + EOL


def error_text(exc: CellvisionError) -> str:
    """The message of an error line: one printable ASCII line of at most MAX_ERROR_TEXT."""
    flat = " ".join(exc.message.split())
    ascii_only = flat.encode("ascii", "replace").decode("ascii")
    if len(ascii_only) > MAX_ERROR_TEXT:
        ascii_only = ascii_only[: MAX_ERROR_TEXT - 3] + "..."
    return ascii_only


def error_line(exc: CellvisionError) -> bytes:
    """``ER <code> <message>``: the code is the binary protocol's ErrorCode number."""
    return f"ER {int(exc.code)} {error_text(exc)}".encode("ascii") + EOL


def result_line(fmt: str, passed: bool, values: Sequence[tuple[float, int]]) -> bytes:
    """A trigger's answer: the verdict (1 pass, 0 fail), then ``values`` as ``(value,
    decimals)``. ``text``: ``OK 1 311.40 208.90``; a controller's format
    (:mod:`.line_formats`): e.g. ``ur``: ``(1, 311.40, 208.90)``. An answer the controller
    could not hold (too long for RAPID's string) is the error INVALID_ARGUMENT instead."""
    numbers = ["1" if passed else "0", *(number_text(v, d) for v, d in values)]
    writer = WRITERS.get(fmt)
    if writer is None:
        return ok_line(*numbers)
    try:
        return writer(numbers)
    except InvalidArgument as exc:
        return trigger_error_line(fmt, exc, None)


def ur_list(numbers: Sequence[str]) -> bytes:
    """``(a, b, c)`` with no end of line (LINE.md §5.2)."""
    return WRITERS["ur"](numbers)


def trigger_error_line(fmt: str, exc: CellvisionError, fields: int | None) -> bytes:
    """The answer to a trigger (or R) that failed. ``text``: the error line. A controller's
    format: the negated code in the verdict's place and a 0 for each of the ``fields`` values
    the inspection answers with, so that a program reading a fixed count gets it (it checks the
    first number): ``(-21, 0, 0)``, ``-21,0,0``. ``fields`` None (the inspection is not known,
    or its answer does not fit): the code alone, ``(-10)``, which a read of more numbers
    reports as a failed read."""
    writer = WRITERS.get(fmt)
    if writer is None:
        return error_line(exc)
    code = str(-int(exc.code))
    try:
        return writer([code] + ["0"] * (fields or 0))
    except InvalidArgument:  # the zeros do not fit either: the code alone does
        return writer([code])


__all__ = [
    "ARITY",
    "EOL",
    "Command",
    "error_line",
    "error_text",
    "number_text",
    "ok_line",
    "parse_line",
    "result_line",
    "trigger_error_line",
    "ur_list",
]
