"""YAML reading with line numbers: a strict reader over ``yaml.safe_load`` output.

Every error names the file, the line and the key path, e.g.
``scene.yaml:12: parts[2].radius: expected a positive number, got -1``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import yaml

__all__ = ["ConfigReader", "SceneError", "load_yaml", "parse_yaml"]

T = TypeVar("T")
PathKey = tuple[str | int, ...]


class SceneError(ValueError):
    """A scene file that cannot be used; the message names file, line and key path."""


def _line_map(node: yaml.Node, path: PathKey, out: dict[PathKey, int]) -> None:
    out[path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            key = key_node.value if isinstance(key_node, yaml.ScalarNode) else str(key_node.value)
            out[(*path, str(key))] = key_node.start_mark.line + 1
            _line_map(value_node, (*path, str(key)), out)
            out[(*path, str(key))] = key_node.start_mark.line + 1
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _line_map(item, (*path, i), out)


def load_yaml(path: Path | str) -> ConfigReader:
    """Read a YAML mapping from ``path``; the returned reader tracks lines for error messages."""
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as exc:
        raise SceneError(f"{file}: cannot read: {exc}") from exc
    return parse_yaml(text, source=str(file))


def parse_yaml(text: str, *, source: str = "<string>") -> ConfigReader:
    try:
        data = yaml.safe_load(text)
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        raise SceneError(f"{source}{line}: invalid YAML: {exc}") from exc
    lines: dict[PathKey, int] = {}
    if node is not None:
        _line_map(node, (), lines)
    if not isinstance(data, dict):
        raise SceneError(f"{source}: the top level must be a mapping")
    return ConfigReader(data, (), source, lines)


def _fmt_path(path: PathKey) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out or "<top>"


class ConfigReader:
    """A view of one mapping in the document; ``take`` keys, then ``finish`` rejects the rest."""

    def __init__(
        self, data: dict[str, Any], path: PathKey, source: str, lines: dict[PathKey, int]
    ) -> None:
        self._data = data
        self._path = path
        self._source = source
        self._lines = lines
        self._seen: set[str] = set()

    @property
    def source(self) -> str:
        return self._source

    def error(self, message: str, key: str | int | None = None) -> SceneError:
        path = self._path if key is None else (*self._path, key)
        probe = path
        while probe and probe not in self._lines:
            probe = probe[:-1]
        line = self._lines.get(probe)
        where = f"{self._source}:{line}" if line is not None else self._source
        return SceneError(f"{where}: {_fmt_path(path)}: {message}")

    def has(self, key: str) -> bool:
        return key in self._data

    def take(self, key: str, convert: Callable[[Any], T], default: T | None = None) -> T:
        """Convert the value at ``key`` (required unless a default is given)."""
        self._seen.add(key)
        if key not in self._data:
            if default is None:
                raise self.error("missing required key", key)
            return default
        try:
            return convert(self._data[key])
        except SceneError:
            raise
        except (TypeError, ValueError) as exc:
            raise self.error(str(exc), key) from exc

    def take_optional(self, key: str, convert: Callable[[Any], T]) -> T | None:
        """Convert the value at ``key``, or None when the key is absent."""
        if key not in self._data:
            self._seen.add(key)
            return None
        return self.take(key, convert)

    def sub_optional(self, key: str) -> ConfigReader | None:
        """The mapping at ``key`` as a reader, or None when the key is absent."""
        self._seen.add(key)
        return self.sub(key) if key in self._data else None

    def sub(self, key: str) -> ConfigReader:
        """The mapping at ``key`` as a reader (required)."""
        self._seen.add(key)
        if key not in self._data:
            raise self.error("missing required key", key)
        value = self._data[key]
        if not isinstance(value, dict):
            raise self.error(f"expected a mapping, got {type(value).__name__}", key)
        return ConfigReader(value, (*self._path, key), self._source, self._lines)

    def items(self, key: str) -> list[ConfigReader]:
        """The list of mappings at ``key`` (an absent key is an empty list)."""
        self._seen.add(key)
        value = self._data.get(key, [])
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.error(f"expected a list, got {type(value).__name__}", key)
        out = []
        for i, item in enumerate(value):
            if not isinstance(item, dict):
                raise ConfigReader({}, (*self._path, key, i), self._source, self._lines).error(
                    f"expected a mapping, got {type(item).__name__}"
                )
            out.append(ConfigReader(item, (*self._path, key, i), self._source, self._lines))
        return out

    def finish(self) -> None:
        unknown = sorted(set(self._data) - self._seen, key=str)
        if unknown:
            raise self.error(f"unknown key (allowed: {', '.join(sorted(self._seen))})", unknown[0])


# Converters: each raises ValueError with a message that says what was expected.


def number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {value!r}")
    out = float(value)
    if out != out or out in (float("inf"), float("-inf")):
        raise ValueError(f"expected a finite number, got {value!r}")
    return out


def positive(value: Any) -> float:
    out = number(value)
    if out <= 0:
        raise ValueError(f"expected a positive number, got {value!r}")
    return out


def non_negative(value: Any) -> float:
    out = number(value)
    if out < 0:
        raise ValueError(f"expected a number >= 0, got {value!r}")
    return out


def probability(value: Any) -> float:
    out = number(value)
    if not 0.0 <= out <= 1.0:
        raise ValueError(f"expected a number in [0, 1], got {value!r}")
    return out


def integer(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"expected an integer, got {value!r}")
    return value


def text(value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"expected a non-empty string, got {value!r}")
    return value


def boolean(value: Any) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f"expected true or false, got {value!r}")
    return value


def vector(n: int) -> Callable[[Any], tuple[float, ...]]:
    def convert(value: Any) -> tuple[float, ...]:
        if not isinstance(value, list) or len(value) != n:
            raise ValueError(f"expected a list of {n} numbers, got {value!r}")
        return tuple(number(v) for v in value)

    return convert


def vec2(value: Any) -> tuple[float, float]:
    v = vector(2)(value)
    return (v[0], v[1])


def vec3(value: Any) -> tuple[float, float, float]:
    v = vector(3)(value)
    return (v[0], v[1], v[2])


def vec5(value: Any) -> tuple[float, float, float, float, float]:
    v = vector(5)(value)
    return (v[0], v[1], v[2], v[3], v[4])


def color(value: Any) -> tuple[float, float, float]:
    """A BGR colour: three numbers in [0, 255], or one gray level."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        value = [value, value, value]
    if not isinstance(value, list) or len(value) != 3:
        raise ValueError(f"expected a BGR colour [b, g, r] or a gray level, got {value!r}")
    out = tuple(number(v) for v in value)
    if not all(0 <= v <= 255 for v in out):
        raise ValueError(f"colour components must be in [0, 255], got {value!r}")
    return (out[0], out[1], out[2])


def one_of(*choices: str) -> Callable[[Any], str]:
    def convert(value: Any) -> str:
        if value not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}, got {value!r}")
        return str(value)

    return convert
