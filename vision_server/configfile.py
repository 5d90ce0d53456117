"""Strict YAML reading for configuration files: ``yaml.safe_load`` semantics (anchors, aliases
and merge keys ``<<: *base`` included), plus the line of every key, duplicate keys refused,
unknown keys refused, and errors that name the file, the line and the key path::

    cell.yaml:41 inspections[2] (name='cap_check') -> threshold: expected a number, got 'high'
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar, overload

import yaml

T = TypeVar("T")
D = TypeVar("D")
Key = str | int
_REQUIRED: Any = object()


class ConfigError(ValueError):
    """A configuration that cannot be used. ``str()`` names file, line, key path and cause."""

    def __init__(
        self, message: str, *, source: str = "", line: int | None = None, path: str = ""
    ) -> None:
        self.source, self.line, self.path, self.reason = source, line, path, message
        where = source + (f":{line}" if line is not None else "")
        parts = [p for p in (where, path) if p]
        super().__init__(f"{' '.join(parts)}: {message}" if parts else message)


MERGE_TAG = "tag:yaml.org,2002:merge"


class _StrictLoader(yaml.SafeLoader):
    """safe_load that refuses duplicate keys (PyYAML silently keeps the last one)."""


def _no_duplicates(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> Any:
    """Construct a mapping, refusing a key written twice. Keys brought in by a merge key
    (``<<: *base``) may be overridden by the mapping's own keys, as YAML's merge says; the
    SafeLoader's ``construct_mapping`` does the merge."""
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == MERGE_TAG:
            continue
        key = loader.construct_object(key_node, deep=True)
        if isinstance(key, list | dict):
            raise yaml.constructor.ConstructorError(
                None, None, "mapping keys must be scalars", key_node.start_mark
            )
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None,
                None,
                f"duplicate key {key!r} (first on line {seen[key]})",
                key_node.start_mark,
            )
        seen[key] = key_node.start_mark.line + 1
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
    _no_duplicates,
)


def _lines(node: yaml.Node | None, path: tuple[Key, ...], out: dict[tuple[Key, ...], int]) -> None:
    if node is None:
        return
    out.setdefault(path, node.start_mark.line + 1)
    if isinstance(node, yaml.MappingNode):
        own = [(k, v) for k, v in node.value if k.tag != MERGE_TAG]
        for key_node, value_node in own:
            child = (*path, str(key_node.value))
            out[child] = key_node.start_mark.line + 1
            _lines(value_node, child, out)
            out[child] = key_node.start_mark.line + 1
        # A merged key is reported at the line where its value is written (the anchored
        # mapping); the mapping's own keys win, and of several merged mappings the first.
        written = {str(k.value) for k, _ in own}
        for merged in _merged_mappings(node):
            for key_node, value_node in merged.value:
                child = (*path, str(key_node.value))
                if str(key_node.value) in written or key_node.tag == MERGE_TAG:
                    continue
                written.add(str(key_node.value))
                _lines(value_node, child, out)
                out[child] = key_node.start_mark.line + 1
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            _lines(item, (*path, index), out)


MAX_EXPANDED_NODES = 100_000
"""Nodes a document may have once its aliases are expanded (a configuration has hundreds):
beyond, aliases of aliases are refused rather than walked (a "billion laughs" document)."""


def _check_aliases(root: yaml.Node | None) -> None:
    """Refuse an alias inside the node it names (``a: &x [*x]``, ``<<: *x`` within ``x``),
    which would never end, and documents whose aliases expand beyond MAX_EXPANDED_NODES."""
    visits = 0
    stack: set[int] = set()

    def walk(node: yaml.Node) -> None:
        nonlocal visits
        visits += 1
        if visits > MAX_EXPANDED_NODES:
            raise yaml.YAMLError(f"more than {MAX_EXPANDED_NODES} nodes once aliases are expanded")
        if id(node) in stack:
            raise yaml.MarkedYAMLError(
                problem="an alias refers to a node that contains it (recursive)",
                problem_mark=node.start_mark,
            )
        if isinstance(node, yaml.SequenceNode):
            stack.add(id(node))
            for item in node.value:
                walk(item)
            stack.discard(id(node))
        elif isinstance(node, yaml.MappingNode):
            stack.add(id(node))
            for key_node, value_node in node.value:
                walk(key_node)
                walk(value_node)
            stack.discard(id(node))

    if root is not None:
        walk(root)


def _merged_mappings(node: yaml.MappingNode) -> list[yaml.MappingNode]:
    """The mappings ``<<:`` brings into ``node`` (``<<: *a`` or ``<<: [*a, *b]``), in order of
    precedence, their own merges included (after them)."""
    out: list[yaml.MappingNode] = []
    for key_node, value_node in node.value:
        if key_node.tag != MERGE_TAG:
            continue
        items = value_node.value if isinstance(value_node, yaml.SequenceNode) else [value_node]
        for item in items:
            if isinstance(item, yaml.MappingNode):
                out.append(item)
                out.extend(_merged_mappings(item))
    return out


def parse_document(text: str, *, source: str) -> Node:
    """Parse YAML text whose top level is a mapping (an empty file is an empty mapping)."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        _check_aliases(root)
        data = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(
            f"invalid YAML: {problem}", source=source, line=None if mark is None else mark.line + 1
        ) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"the top level must be a mapping, got {type(data).__name__}", source=source, line=1
        )
    lines: dict[tuple[Key, ...], int] = {}
    _lines(root, (), lines)
    return Node(data, (), source, lines, {})


def read_document(path: Path) -> tuple[Node, str]:
    """Read and parse a configuration file; also returns its text (for hashing)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the file: {exc}", source=str(path)) from None
    return parse_document(text, source=path.name), text


class Node:
    """A view of one mapping in a document: ``take`` what you know, then ``finish()``, which
    refuses every key that was not taken."""

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

    # ------------------------------------------------------------------ errors

    def describe(self, key: Key | None = None) -> str:
        path = self.path if key is None else (*self.path, key)
        out: list[str] = []
        for i, part in enumerate(path):
            if isinstance(part, int):
                label = self._labels.get(path[: i + 1], "")
                out[-1] = f"{out[-1]}[{part}]" + (f" ({label})" if label else "")
            else:
                out.append(str(part))
        return " -> ".join(out)

    def error(self, message: str, key: Key | None = None) -> ConfigError:
        path = self.path if key is None else (*self.path, key)
        probe = path
        while probe and probe not in self._lines:
            probe = probe[:-1]
        return ConfigError(
            message, source=self.source, line=self._lines.get(probe), path=self.describe(key)
        )

    # ------------------------------------------------------------------ reading

    def __contains__(self, key: str) -> bool:
        return key in self.data

    @overload
    def take(self, key: str, convert: Callable[[Any], T]) -> T: ...

    @overload
    def take(self, key: str, convert: Callable[[Any], T], default: D) -> T | D: ...

    def take(self, key: str, convert: Callable[[Any], T], default: Any = _REQUIRED) -> Any:
        """The value at ``key`` through ``convert`` (which raises ValueError/TypeError with a
        message saying what was expected). Without a default the key is required; a default
        is returned as it is (not converted)."""
        self._taken.add(key)
        if key not in self.data or self.data[key] is None:
            if default is _REQUIRED:
                raise self.error(f"missing required key {key!r}")
            return default
        try:
            return convert(self.data[key])
        except ConfigError:
            raise
        except (TypeError, ValueError) as exc:
            raise self.error(str(exc), key) from None

    def sub(self, key: str, *, required: bool = False) -> Node:
        """The mapping at ``key`` (an absent optional key reads as an empty mapping)."""
        self._taken.add(key)
        value = self.data.get(key)
        if value is None:
            if required:
                raise self.error(f"missing required key {key!r}")
            value = {}
        if not isinstance(value, dict):
            raise self.error(f"expected a mapping, got {_kind(value)}", key)
        return Node(value, (*self.path, key), self.source, self._lines, self._labels)

    def has(self, key: str) -> bool:
        return self.data.get(key) is not None

    def items(self, key: str) -> list[Node]:
        """The list of mappings at ``key`` (absent: empty). Items with a ``name`` are labelled
        with it in error messages."""
        self._taken.add(key)
        value = self.data.get(key)
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.error(f"expected a list, got {_kind(value)}", key)
        nodes = []
        for index, item in enumerate(value):
            path = (*self.path, key, index)
            if isinstance(item, dict) and isinstance(item.get("name"), str):
                self._labels[path] = f"name={item['name']!r}"
            if not isinstance(item, dict):
                raise Node({}, path, self.source, self._lines, self._labels).error(
                    f"expected a mapping, got {_kind(item)}"
                )
            nodes.append(Node(item, path, self.source, self._lines, self._labels))
        return nodes

    def named(self, key: str) -> Iterator[tuple[str, Node]]:
        """The mapping of names to mappings at ``key`` (absent: empty)."""
        sub = self.sub(key)
        for name, value in sub.data.items():
            sub._taken.add(str(name))
            if not isinstance(name, str) or not NAME.fullmatch(name):
                raise sub.error(
                    f"bad name {name!r}: use letters, digits, '_', '-' and '.'",
                )
            if not isinstance(value, dict):
                raise sub.error(f"expected a mapping, got {_kind(value)}", name)
            yield name, Node(value, (*sub.path, name), self.source, self._lines, self._labels)

    def finish(self) -> None:
        unknown = [k for k in self.data if str(k) not in self._taken]
        if unknown:
            allowed = ", ".join(sorted(self._taken)) or "none"
            raise self.error(f"unknown key (allowed here: {allowed})", str(unknown[0]))


NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")


def _kind(value: Any) -> str:
    if value is None:
        return "nothing"
    return {dict: "a mapping", list: "a list", str: f"{value!r}", bool: f"{value!r}"}.get(
        type(value), f"{value!r}"
    )


# ----------------------------------------------------------------------------- converters
# Each raises ValueError with a message that says what was expected and what came.


def number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {_kind(value)}")
    if not math.isfinite(value):
        raise ValueError(f"expected a finite number, got {value!r}")
    return float(value)


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
        raise ValueError(f"expected an integer, got {_kind(value)}")
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
        raise ValueError(f"expected true or false, got {_kind(value)}")
    return value


def string(value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"expected a non-empty string, got {_kind(value)}")
    return value


def name(value: Any) -> str:
    out = string(value)
    if not NAME.fullmatch(out):
        raise ValueError(f"bad name {out!r}: use letters, digits, '_', '-' and '.' (max 64)")
    return out


def one_of(*choices: str) -> Callable[[Any], str]:
    def convert(value: Any) -> str:
        if value not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}; got {_kind(value)}")
        return str(value)

    return convert


def numbers(
    count: int | None = None, *, each: Callable[[Any], float] = number
) -> Callable[[Any], tuple[float, ...]]:
    def convert(value: Any) -> tuple[float, ...]:
        if not isinstance(value, list) or (count is not None and len(value) != count):
            want = f"a list of {count} numbers" if count is not None else "a list of numbers"
            raise ValueError(f"expected {want}, got {_kind(value)}")
        return tuple(each(v) for v in value)

    return convert


def roi(value: Any) -> tuple[int, int, int, int]:
    """An ROI ``[u, v, width, height]`` in whole pixels."""
    if not isinstance(value, list) or len(value) != 4:
        raise ValueError(f"expected [u, v, width, height], got {_kind(value)}")
    u, v, w, h = (integer(x) for x in value)
    if u < 0 or v < 0 or w <= 0 or h <= 0:
        raise ValueError(
            f"ROI [u, v, width, height] needs u, v >= 0 and a positive size, got {value!r}"
        )
    return u, v, w, h
