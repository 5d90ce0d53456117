"""Parsing a YAML file into a :class:`~yamlfile.node.Node`: ``yaml.safe_load`` semantics
(anchors, aliases and merge keys ``<<: *base`` included) plus the line of every key, duplicate
keys refused, and aliases that never end or expand beyond :data:`MAX_EXPANDED_NODES` refused.
Only a SafeLoader subclass ever constructs a value, so no tag can run code.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar, overload

import yaml

from .node import Key, Node

__all__ = ["MAX_EXPANDED_NODES", "parse_document", "read_document"]

N = TypeVar("N", bound=Node)

MERGE_TAG = "tag:yaml.org,2002:merge"


class _StrictLoader(yaml.SafeLoader):
    """safe_load that refuses duplicate keys (PyYAML silently keeps the last one). ``paths``
    gives the key path of each mapping node (by id) for the error."""

    paths: dict[int, tuple[Key, ...]]


class _DuplicateKey(Exception):
    """``key`` written twice in the mapping at ``path``, first on line ``first``."""

    def __init__(self, path: tuple[Key, ...], key: str, first: int) -> None:
        super().__init__(path, key, first)
        self.path, self.key, self.first = path, key, first


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
            raise _DuplicateKey(loader.paths.get(id(node), ()), str(key), seen[key])
        seen[key] = key_node.start_mark.line + 1
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
    _no_duplicates,
)


def _lines(
    node: yaml.Node | None,
    path: tuple[Key, ...],
    out: dict[tuple[Key, ...], int],
    mappings: dict[int, tuple[Key, ...]],
) -> None:
    """Record in ``out`` the line of every key path below ``node`` (a key written twice: the
    second), and in ``mappings`` the path of every mapping node (where it is first met)."""
    if node is None:
        return
    out.setdefault(path, node.start_mark.line + 1)
    if isinstance(node, yaml.MappingNode):
        mappings.setdefault(id(node), path)
        own = [(k, v) for k, v in node.value if k.tag != MERGE_TAG]
        for key_node, value_node in own:
            child = (*path, str(key_node.value))
            out[child] = key_node.start_mark.line + 1
            _lines(value_node, child, out, mappings)
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
                _lines(value_node, child, out, mappings)
                out[child] = key_node.start_mark.line + 1
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            _lines(item, (*path, index), out, mappings)


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


@overload
def parse_document(text: str, *, source: str) -> Node: ...


@overload
def parse_document(text: str, *, source: str, node_type: type[N]) -> N: ...


def parse_document(text: str, *, source: str, node_type: type[Node] = Node) -> Node:
    """Parse YAML text whose top level is a mapping (an empty file is an empty mapping) into a
    ``node_type`` (whose ``error_type`` every error of the file is raised as). ``source`` is
    the file's name as errors show it."""
    error = node_type.error_type
    lines: dict[tuple[Key, ...], int] = {}
    try:
        root = yaml.compose(text, Loader=_StrictLoader)
        _check_aliases(root)
        mappings: dict[int, tuple[Key, ...]] = {}
        _lines(root, (), lines, mappings)
        # Construct from the nodes just walked, so that a duplicate key's mapping is known by
        # its path (yaml.load would compose the text again).
        constructor = _StrictLoader("")
        constructor.paths = mappings
        data = None if root is None else constructor.construct_document(root)
    except _DuplicateKey as dup:
        where = node_type({}, dup.path, source, lines, {})
        raise where.error(
            f"duplicate key {dup.key!r} (first on line {dup.first})", dup.key
        ) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        raise error(
            f"invalid YAML: {problem}", source=source, line=None if mark is None else mark.line + 1
        ) from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise error(
            f"the top level must be a mapping, got {type(data).__name__}", source=source, line=1
        )
    return node_type(data, (), source, lines, {})


@overload
def read_document(path: Path, *, source: str | None = None) -> tuple[Node, str]: ...


@overload
def read_document(
    path: Path, *, source: str | None = None, node_type: type[N]
) -> tuple[N, str]: ...


def read_document(
    path: Path, *, source: str | None = None, node_type: type[Node] = Node
) -> tuple[Node, str]:
    """Read and parse a file (UTF-8); also returns its text (for hashing). Errors show the
    file as ``source`` (default: ``path`` as given)."""
    shown = str(path) if source is None else source
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise node_type.error_type(
            f"cannot read the file: {_os_reason(exc)}", source=str(path)
        ) from None
    except UnicodeDecodeError as exc:
        raise node_type.error_type(
            f"cannot read the file: not a YAML text file (byte 0x{exc.object[exc.start]:02x} at "
            f"offset {exc.start} is not UTF-8 text: an image or another binary file?)",
            source=str(path),
        ) from None
    return parse_document(text, source=shown, node_type=node_type), text


def _os_reason(exc: OSError) -> str:
    """Why a file could not be read, in words (``[Errno 2] No such file...: 'p'`` names the
    file again, which the error's source already does)."""
    if isinstance(exc, FileNotFoundError):
        return "no such file"
    if isinstance(exc, IsADirectoryError):
        return "it is a directory, not a file"
    if isinstance(exc, PermissionError):
        return "permission denied"
    return exc.strerror or str(exc)
