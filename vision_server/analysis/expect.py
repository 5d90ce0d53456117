"""What a read code must say (an inspection's ``expect``): a text, exactly, or a pattern the
whole payload must match.

A pattern is compiled by RE2 (google-re2), whose matching takes time linear in the text: the
payload comes from whatever label a part carries, and Python's ``re`` backtracks, so that a
pattern such as ``(a+)+$`` on a label of 40 ``a`` and a ``!`` held the interpreter for minutes
and froze the whole server, robots' connections included. RE2's syntax is Python's without
backreferences and lookaround (docs/configuration.md, "expect").
"""

from __future__ import annotations

from typing import Protocol

import re2

MAX_PATTERN = 1000
"""The longest pattern, characters (a payload's pattern, not a program)."""
MAX_PROGRAM_BYTES = 1 << 20
"""RE2's memory for one compiled pattern, bytes (its own default is 8 MiB)."""


class Pattern(Protocol):
    """A compiled pattern: the whole text matches or not."""

    @property
    def pattern(self) -> str: ...

    def fullmatch(self, text: str) -> object | None: ...


Expect = str | Pattern | None
"""Exact text, a :class:`Pattern`, or None (any payload)."""


class PatternError(ValueError):
    """A pattern RE2 does not take; the message says why."""


def compile_pattern(pattern: str) -> Pattern:
    """``pattern`` compiled for full matches in linear time; :class:`PatternError` when it is
    too long or not RE2 syntax (a backreference, a lookaround)."""
    if len(pattern) > MAX_PATTERN:
        raise PatternError(f"the pattern has {len(pattern)} characters, at most {MAX_PATTERN}")
    options = re2.Options()
    options.log_errors = False  # the error is raised to the caller, not printed by RE2
    options.max_mem = MAX_PROGRAM_BYTES
    try:
        compiled: Pattern = re2.compile(pattern, options)
    except re2.error as exc:
        reason = exc.args[0] if exc.args else exc
        if isinstance(reason, bytes):
            reason = reason.decode("utf-8", "replace")
        raise PatternError(
            f"{reason} (RE2 syntax: Python's without backreferences or lookaround)"
        ) from None
    return compiled


def matches(text: str, expect: Expect) -> bool:
    """Whether the payload ``text`` is what ``expect`` asks (None: any)."""
    if expect is None:
        return True
    if isinstance(expect, str):
        return text == expect
    return expect.fullmatch(text) is not None


def describe(expect: Expect) -> str:
    """``expect`` for a message: the text quoted, or ``pattern '...'``."""
    if expect is None or isinstance(expect, str):
        return repr(expect)
    return f"pattern {expect.pattern!r}"


__all__ = ["Expect", "Pattern", "PatternError", "compile_pattern", "describe", "matches"]
