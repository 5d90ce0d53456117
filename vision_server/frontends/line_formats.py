"""How a trigger's numbers are written for each robot controller (protocol/LINE.md §5).

Each format is shaped by what that controller's own functions parse with no code of the
program's: URScript's ``socket_read_ascii_float`` (a parenthesised list), RAPID's
``SocketReceive`` into an 80-character ``string`` then ``StrToVal`` on comma-separated fields,
KRL's EthernetKRL stream element then ``SREAD`` on blank-separated fields, KAREL's ``READ`` of
a ``STRING`` then ``CNV_STR_REAL`` on fixed-width fields. A format gets the numbers already
written in fixed point (:func:`.line_codec.number_text`); it joins them, or refuses with
INVALID_ARGUMENT when the controller could not hold the answer.
"""

from __future__ import annotations

from collections.abc import Sequence

from protocol import InvalidArgument

EOL = "\r\n"

ABB_MAX_CHARS = 80
"""RAPID's ``string`` holds at most 80 characters: one SocketReceive \\Str gets the whole
answer, its CR LF included."""
KAREL_MAX_CHARS = 254
"""KAREL's longest ``STRING[n]``."""
KRL_MAX_CHARS = 254
"""What the server lets a ``kuka`` answer be: the EKI stream element's ``Size`` (and the
program's CHAR array) must be at least this, or at least the answer its inspection gives."""
FANUC_FIELD = 12
"""Characters of every field of a ``fanuc`` answer (the verdict too): field i (from 1) is
``SUB_STR(answer, 12 * (i - 1) + 1, 12)``."""


def ur(numbers: Sequence[str]) -> bytes:
    """``(a, b, c)`` with no end of line: socket_read_ascii_float stops at the parenthesis,
    and a line end after it would be what the program's next socket_read_line returns."""
    return ("(" + ", ".join(numbers) + ")").encode("ascii")


def abb(numbers: Sequence[str]) -> bytes:
    """``a,b,c`` CR LF, at most 80 characters: the program splits at the commas (StrFind,
    StrPart) and converts each field with StrToVal."""
    text = ",".join(numbers) + EOL
    return _within(text, ABB_MAX_CHARS, "abb", "RAPID's string")


def kuka(numbers: Sequence[str]) -> bytes:
    """``a b c`` CR LF: the EKI stream element ends at CR LF (``EOS="13,10"``), and SREAD
    reads the fields with ``"%d %f %f"`` (blanks separate them)."""
    text = " ".join(numbers) + EOL
    return _within(text, KRL_MAX_CHARS, "kuka", "the EKI stream element")


def fanuc(numbers: Sequence[str]) -> bytes:
    """Every number right-aligned, zero-padded to 12 characters (``-0000311.400``), then CR
    LF: the program cuts fields with SUB_STR at fixed places and converts each with
    CNV_STR_REAL. Zeros rather than blanks, since a blank is not part of a KAREL number."""
    fields = [_zero_padded(n) for n in numbers]
    text = "".join(fields) + EOL
    return _within(text, KAREL_MAX_CHARS, "fanuc", "KAREL's STRING")


def _zero_padded(number: str) -> str:
    sign, digits = ("-", number[1:]) if number.startswith("-") else ("", number)
    width = FANUC_FIELD - len(sign)
    if len(digits) > width:
        raise InvalidArgument(
            f"the value {number} does not fit a fanuc field of {FANUC_FIELD} characters; "
            "give the output fewer decimals or a smaller scale"
        )
    return sign + digits.rjust(width, "0")


def _within(text: str, limit: int, name: str, holder: str) -> bytes:
    if len(text) > limit:
        raise InvalidArgument(
            f"the {name} answer has {len(text)} characters, more than {holder} holds "
            f"({limit}); give the output fewer values or decimals"
        )
    return text.encode("ascii")


WRITERS = {"ur": ur, "abb": abb, "kuka": kuka, "fanuc": fanuc}
"""The controller formats by name; ``text`` (``OK`` and the numbers) is the codec's own."""

__all__ = ["ABB_MAX_CHARS", "FANUC_FIELD", "KAREL_MAX_CHARS", "KRL_MAX_CHARS", "WRITERS"]
