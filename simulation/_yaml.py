"""Scene files' YAML reading: the project's one reader (:mod:`yamlfile`) with its errors raised
as :class:`SceneError`, and the scene's own converters (vectors, colours).

Every error names the file, the line and the key path, e.g.
``scene.yaml:12 parts[2] (name='cap_1') -> radius: expected a number > 0, got -1``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

from yamlfile import (
    DocumentError,
    Key,
    Node,
    boolean,
    fraction,
    integer,
    non_negative,
    number,
    numbers,
    one_of,
    parse_document,
    positive,
    read_document,
    string,
)

__all__ = [
    "SceneError",
    "SceneNode",
    "boolean",
    "color",
    "fraction",
    "integer",
    "load_yaml",
    "non_negative",
    "number",
    "one_of",
    "parse_yaml",
    "positive",
    "string",
    "vec2",
    "vec3",
    "vec5",
]


class SceneError(DocumentError):
    """A scene file that cannot be used; the message names file, line and key path."""


class SceneNode(Node):
    """A mapping of a scene file; errors are SceneErrors."""

    error_type = SceneError

    def error(self, message: str, key: Key | None = None) -> SceneError:
        """As :meth:`yamlfile.Node.error`, typed as the SceneError it returns."""
        return cast(SceneError, super().error(message, key))


def load_yaml(path: Path | str) -> SceneNode:
    """Read a scene file's top-level mapping; errors show the file as ``path`` is given."""
    node, _ = read_document(Path(path), node_type=SceneNode)
    return node


def parse_yaml(text: str, *, source: str = "<string>") -> SceneNode:
    """Parse scene text; errors show the file as ``source``."""
    return parse_document(text, source=source, node_type=SceneNode)


# Converters of the scene's own values; the plain ones (number, positive, non_negative,
# fraction, integer, string, boolean, one_of) are yamlfile's. Each raises ValueError.


def vec2(value: Any) -> tuple[float, float]:
    v = numbers(2)(value)
    return (v[0], v[1])


def vec3(value: Any) -> tuple[float, float, float]:
    v = numbers(3)(value)
    return (v[0], v[1], v[2])


def vec5(value: Any) -> tuple[float, float, float, float, float]:
    v = numbers(5)(value)
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
