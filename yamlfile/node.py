"""A view of one mapping of a parsed document, and the error every reader raises.

``take`` what you know, then ``finish()``, which refuses every key that was not taken. Errors
name the file, the line and the key path::

    cell.yaml:41 inspections[2] (name='cap_check') -> threshold: expected a number, got 'high'
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Iterator
from typing import Any, ClassVar, Self, TypeVar, overload

from .convert import NAME, kind

__all__ = ["DocumentError", "Key", "Node"]

T = TypeVar("T")
D = TypeVar("D")
Key = str | int
_REQUIRED: Any = object()


class DocumentError(ValueError):
    """A YAML file that cannot be used. ``str()`` names file, line, key path and cause; the
    parts are attributes too (``source``, ``line`` (1-based, None if unknown), ``path``,
    ``reason``). Each kind of file has its own subclass (``ConfigError``, ``SceneError``...)."""

    def __init__(
        self, message: str, *, source: str = "", line: int | None = None, path: str = ""
    ) -> None:
        self.source, self.line, self.path, self.reason = source, line, path, message
        where = source + (f":{line}" if line is not None else "")
        parts = [p for p in (where, path) if p]
        super().__init__(f"{' '.join(parts)}: {message}" if parts else message)


class Node:
    """One mapping of a document at key path ``path``, read from ``source`` (the file's name as
    errors show it). ``lines`` maps key paths to 1-based lines; ``labels`` maps list items to
    the label shown after their index (``name='caps'``). Subclasses set ``error_type`` so that
    each kind of file raises its own error class; nodes below keep the subclass."""

    error_type: ClassVar[type[DocumentError]] = DocumentError

    def __init__(
        self,
        data: dict[Any, Any],
        path: tuple[Key, ...],
        source: str,
        lines: dict[tuple[Key, ...], int],
        labels: dict[tuple[Key, ...], str],
    ) -> None:
        self.data = data
        self.path = path
        self.source = source
        self._lines = lines
        self._labels = labels
        self._taken: set[str] = set()

    def _child(self, data: dict[Any, Any], path: tuple[Key, ...]) -> Self:
        return type(self)(data, path, self.source, self._lines, self._labels)

    # ------------------------------------------------------------------ errors

    def describe(self, key: Key | None = None) -> str:
        """The key path as errors show it: ``inspections[2] (name='caps') -> roi``."""
        path = self.path if key is None else (*self.path, key)
        out: list[str] = []
        for i, part in enumerate(path):
            if isinstance(part, int):
                label = self._labels.get(path[: i + 1], "")
                shown = f"[{part}]" + (f" ({label})" if label else "")
                if out:
                    out[-1] += shown
                else:
                    out.append(shown)
            else:
                out.append(str(part))
        return " -> ".join(out)

    def line(self, key: Key | None = None) -> int | None:
        """The 1-based line of ``key`` (of this mapping without one), or of the nearest
        enclosing key the document records; None when the node was not read from a file."""
        probe = self.path if key is None else (*self.path, key)
        while probe and probe not in self._lines:
            probe = probe[:-1]
        return self._lines.get(probe)

    def error(self, message: str, key: Key | None = None) -> DocumentError:
        """The error to raise for ``message`` at ``key`` (at this mapping without one)."""
        return self.error_type(
            message, source=self.source, line=self.line(key), path=self.describe(key)
        )

    # ------------------------------------------------------------------ reading

    def __contains__(self, key: str) -> bool:
        return key in self.data

    def has(self, key: str) -> bool:
        """Whether ``key`` is given a value (a key written as ``null`` is not)."""
        return self.data.get(key) is not None

    @overload
    def take(self, key: str, convert: Callable[[Any], T]) -> T: ...

    @overload
    def take(self, key: str, convert: Callable[[Any], T], default: D) -> T | D: ...

    def take(self, key: str, convert: Callable[[Any], T], default: Any = _REQUIRED) -> Any:
        """The value at ``key`` through ``convert`` (which raises ValueError/TypeError with a
        message saying what was expected). Without a default the key is required; a default
        is returned as it is (not converted). ``null`` reads as absent."""
        self._taken.add(key)
        if key not in self.data or self.data[key] is None:
            if default is _REQUIRED:
                raise self.error(f"missing required key {key!r}{self._typo_of(key)}")
            return default
        try:
            return convert(self.data[key])
        except DocumentError:
            raise
        except (TypeError, ValueError) as exc:
            raise self.error(str(exc), key) from None

    def sub(self, key: str, *, required: bool = False) -> Self:
        """The mapping at ``key`` (an absent optional key reads as an empty mapping)."""
        self._taken.add(key)
        value = self.data.get(key)
        if value is None:
            if required:
                raise self.error(f"missing required key {key!r}{self._typo_of(key)}")
            value = {}
        if not isinstance(value, dict):
            raise self.error(f"expected a mapping, got {kind(value)}", key)
        return self._child(value, (*self.path, key))

    def sub_optional(self, key: str) -> Self | None:
        """The mapping at ``key``, or None when it is absent (or ``null``)."""
        self._taken.add(key)
        return self.sub(key) if self.has(key) else None

    def items(self, key: str) -> list[Self]:
        """The list of mappings at ``key`` (absent: empty). Items with a ``name`` are labelled
        with it in error messages."""
        self._taken.add(key)
        value = self.data.get(key)
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.error(f"expected a list, got {kind(value)}", key)
        nodes = []
        for index, item in enumerate(value):
            path = (*self.path, key, index)
            if isinstance(item, dict) and isinstance(item.get("name"), str):
                self._labels[path] = f"name={item['name']!r}"
            if not isinstance(item, dict):
                raise self._child({}, path).error(f"expected a mapping, got {kind(item)}")
            nodes.append(self._child(item, path))
        return nodes

    def label(self, text: str) -> None:
        """Show ``text`` after this list item's index in error messages (``[0] (place/a)``)."""
        if self.path and isinstance(self.path[-1], int):
            self._labels[self.path] = text

    def named(self, key: str) -> Iterator[tuple[str, Self]]:
        """The mapping of names to mappings at ``key`` (absent: empty)."""
        sub = self.sub(key)
        for name, value in sub.data.items():
            sub._taken.add(str(name))
            if not isinstance(name, str) or not NAME.fullmatch(name):
                raise sub.error(
                    f"bad name {name!r}: use letters, digits, '_', '-' and '.'",
                )
            if not isinstance(value, dict):
                raise sub.error(f"expected a mapping, got {kind(value)}", name)
            yield name, sub._child(value, (*sub.path, name))

    def _typo_of(self, key: str) -> str:
        """``" (is 'mesure' a typo of it?)"`` when a key not read yet looks like ``key``: a
        misspelt required key is reported where it is missing, so name the misspelling too."""
        others = [str(k) for k in self.data if str(k) not in self._taken and str(k) != key]
        close = difflib.get_close_matches(key, others, n=1, cutoff=0.75)
        return f" (is {close[0]!r} a typo of it?)" if close else ""

    def finish(self) -> None:
        """Refuse the first key that was not taken (a typo, or a key of another version)."""
        unknown = [k for k in self.data if str(k) not in self._taken]
        if unknown:
            allowed = ", ".join(sorted(self._taken)) or "none"
            raise self.error(f"unknown key (allowed here: {allowed})", str(unknown[0]))
