"""yamlfile: the one reader of every YAML file the project reads (the server's configuration,
scenes, task files, taught records). Imports nothing of ours; PyYAML's safe loading only.

It keeps ``yaml.safe_load``'s meaning (anchors, aliases, merge keys ``<<: *base``) and adds
what a person editing a file needs: duplicate keys and self-referencing or exploding aliases
are refused, unknown keys are refused (``Node.finish``), and every error names the file, the
line and the key path::

    cell.yaml:41 inspections[2] (name='cap_check') -> threshold: expected a number, got 'high'

Public API:

- ``parse_document(text, *, source, node_type=Node) -> Node`` and
  ``read_document(path, *, source=None, node_type=Node) -> (Node, text)``: the top-level
  mapping of a document; ``MAX_EXPANDED_NODES`` bounds what aliases may expand to.
- ``Node``: ``take(key, convert[, default])``, ``sub``, ``sub_optional``, ``items``, ``named``,
  ``has``, ``finish``, ``error(message, key)``, ``line(key)``, ``describe(key)``, ``label``.
  A file kind subclasses it and sets ``error_type`` to its own ``DocumentError`` subclass.
- ``DocumentError(message, *, source, line, path)``: the error of every reader.
- Converters for ``take`` (each raises ValueError saying what was expected): ``number``,
  ``positive``, ``non_negative``, ``fraction``, ``integer``, ``positive_int``,
  ``non_negative_int``, ``boolean``, ``string``, ``name`` (``NAME``), ``one_of(*choices)``,
  ``numbers(count)``; ``kind(value)`` shows a value in a message.
"""

from .convert import (
    NAME,
    boolean,
    fraction,
    integer,
    kind,
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
from .document import MAX_EXPANDED_NODES, parse_document, read_document
from .node import DocumentError, Key, Node

__all__ = [
    "MAX_EXPANDED_NODES",
    "NAME",
    "DocumentError",
    "Key",
    "Node",
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
    "parse_document",
    "positive",
    "positive_int",
    "read_document",
    "string",
]
