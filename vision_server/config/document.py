"""The server configuration's YAML reading: the project's one reader (:mod:`yamlfile`) with
its errors raised as :class:`ConfigError`::

    cell.yaml:41 inspections[2] (name='cap_check') -> threshold: expected a number, got 'high'
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import yamlfile
from yamlfile import (
    MAX_EXPANDED_NODES,
    NAME,
    DocumentError,
    Key,
    boolean,
    fraction,
    integer,
    name,
    non_negative,
    non_negative_int,
    number,
    numbers,
    one_of,
    positive,
    positive_int,
    string,
)

__all__ = [
    "MAX_EXPANDED_NODES",
    "NAME",
    "ConfigError",
    "Key",
    "Node",
    "boolean",
    "fraction",
    "integer",
    "name",
    "non_negative",
    "non_negative_int",
    "number",
    "numbers",
    "one_of",
    "parse_document",
    "positive",
    "positive_int",
    "read_document",
    "string",
]


class ConfigError(DocumentError):
    """A configuration that cannot be used. ``str()`` names file, line, key path and cause."""


class Node(yamlfile.Node):
    """A mapping of the configuration (or of a request's options); errors are ConfigErrors."""

    error_type = ConfigError

    def error(self, message: str, key: Key | None = None) -> ConfigError:
        """As :meth:`yamlfile.Node.error`, typed as the ConfigError it returns."""
        return cast(ConfigError, super().error(message, key))


def parse_document(text: str, *, source: str) -> Node:
    """Parse configuration text whose top level is a mapping (an empty file is an empty one)."""
    return yamlfile.parse_document(text, source=source, node_type=Node)


def read_document(path: Path) -> tuple[Node, str]:
    """Read and parse a configuration file; also returns its text (for hashing). Errors show
    the file's name only: they go to clients (RELOAD), which need not see the server's paths."""
    return yamlfile.read_document(path, source=path.name, node_type=Node)
