"""Saving an inspection's tuned keys from the console into the configuration file.

The file is edited as text, not re-dumped: only the values of the changed keys are replaced
(a key the inspection does not have yet is added under it), so that comments, order and
anchors elsewhere stay as the integrator wrote them. The new text is validated by the same
loader as ``serve`` (:func:`vision_server.config.parse_config`) before anything is written; the
old file is kept as ``NAME.bak-YYYYmmddTHHMMSS``; the file is replaced atomically.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from ..config import FIXED_BY_THE_CONFIGURATION, ConfigError, parse_config, parse_document


class SaveRefused(ValueError):
    """The edit cannot be made; the message names the file, the key and the cause."""


def edited_text(text: str, source: str, inspection: str, options: Mapping[str, Any]) -> str:
    """``text`` with the keys ``options`` (dotted for nested ones: ``circle.min_radius_px``)
    of inspection ``inspection`` set to their values. Raises :class:`SaveRefused`."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise SaveRefused(f"{source}: the file is not valid YAML: {exc}") from None
    item = _inspection_node(root, source, inspection)
    edits: list[tuple[int, int, str]] = []
    for key, value in options.items():
        _check_option(source, inspection, key, value)
        parts = key.split(".")
        node = item
        for part in parts[:-1]:
            child = _value_of(node, part)
            if not isinstance(child, yaml.MappingNode):
                raise SaveRefused(
                    f"{source}: inspection {inspection!r} -> {key}: {part!r} is not a mapping "
                    "in the file; edit it by hand"
                )
            node = child
        edits.append(_set(text, source, inspection, key, node, parts[-1], value, item))
    out = text
    for start, end, replacement in sorted(edits, key=lambda e: e[0], reverse=True):
        out = out[:start] + replacement + out[end:]
    return out


def validate(text: str, path: Path) -> None:
    """The configuration ``text`` (to be saved as ``path``) as ``serve`` would load it;
    raises ConfigError naming file, line and key path."""
    root = parse_document(text, source=path.name)
    parse_config(root, text=text, base_dir=path.resolve().parent, source=path)


def write_with_backup(path: Path, text: str) -> Path:
    """Keep the current file as a backup beside it, then replace it with ``text`` atomically;
    returns the backup's path."""
    old = path.read_bytes()
    stamp = time.strftime("%Y%m%dT%H%M%S")
    backup = path.with_name(f"{path.name}.bak-{stamp}")
    n = 1
    while backup.exists():
        n += 1
        backup = path.with_name(f"{path.name}.bak-{stamp}-{n}")
    backup.write_bytes(old)
    replace_file(path, text.encode("utf-8"))
    return backup


def replace_file(path: Path, data: bytes) -> None:
    """Write ``data`` as ``path`` atomically (a temporary file beside it, then rename)."""
    tmp = path.with_name(f".{path.name}.console-{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        with contextlib.suppress(OSError):
            os.chmod(tmp, path.stat().st_mode & 0o777)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


# ----------------------------------------------------------------------------- helpers


def _check_option(source: str, inspection: str, key: str, value: Any) -> None:
    where = f"{source}: inspection {inspection!r} -> {key}"
    if not key or any(not part for part in key.split(".")):
        raise SaveRefused(f"{where}: not a key")
    if key.split(".")[0] in FIXED_BY_THE_CONFIGURATION:
        raise SaveRefused(f"{where}: cannot be changed from the console")
    if not _plain(value):
        raise SaveRefused(f"{where}: expected a number, a string, a boolean or a list of them")


def _plain(value: Any) -> bool:
    if isinstance(value, bool | int | str):
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, list):
        return all(isinstance(v, bool | int | float | str) and _plain(v) for v in value)
    return False


def _inspection_node(root: Any, source: str, name: str) -> yaml.MappingNode:
    inspections = _value_of(root, "inspections") if isinstance(root, yaml.MappingNode) else None
    if not isinstance(inspections, yaml.SequenceNode):
        raise SaveRefused(f"{source}: the file has no list of inspections")
    for item in inspections.value:
        if not isinstance(item, yaml.MappingNode):
            continue
        named = _value_of(item, "name")
        if isinstance(named, yaml.ScalarNode) and named.value == name:
            return item
    raise SaveRefused(f"{source}: the file has no inspection named {name!r}")


def _value_of(node: yaml.MappingNode, key: str) -> yaml.Node | None:
    for key_node, value_node in node.value:
        if isinstance(key_node, yaml.ScalarNode) and key_node.value == key:
            found: yaml.Node = value_node
            return found
    return None


def _set(
    text: str,
    source: str,
    inspection: str,
    dotted: str,
    node: yaml.MappingNode,
    key: str,
    value: Any,
    item: yaml.MappingNode,
) -> tuple[int, int, str]:
    """The edit that makes ``key`` of ``node`` hold ``value``: (start, end, replacement)."""
    rendered = _flow(value)
    current = _value_of(node, key)
    inside = item.start_mark.index <= node.start_mark.index < item.end_mark.index
    if not inside:
        raise SaveRefused(
            f"{source}: inspection {inspection!r} -> {dotted}: it comes from an anchor shared "
            "with other entries; edit it by hand"
        )
    if current is not None:
        if not item.start_mark.index <= current.start_mark.index < item.end_mark.index:
            raise SaveRefused(
                f"{source}: inspection {inspection!r} -> {dotted}: its value is an alias of "
                "an anchor shared with other entries; edit it by hand"
            )
        return current.start_mark.index, current.end_mark.index, rendered
    if node.flow_style:
        # "{a: 1, b: 2}": add ", key: value" before the closing brace.
        close = text.rindex("}", node.start_mark.index, node.end_mark.index)
        sep = ", " if node.value else ""
        return close, close, f"{sep}{key}: {rendered}"
    if not node.value:
        raise SaveRefused(f"{source}: inspection {inspection!r} -> {dotted}: edit it by hand")
    first_key = node.value[0][0]
    indent = " " * first_key.start_mark.column
    last_value = node.value[-1][1]
    line_end = text.find("\n", last_value.end_mark.index)
    if line_end < 0:
        line_end = len(text)
    return line_end, line_end, f"\n{indent}{key}: {rendered}"


def _flow(value: Any) -> str:
    """``value`` as YAML in flow style on one line."""
    dumped = yaml.safe_dump(value, default_flow_style=True, width=1 << 30)
    return dumped.removesuffix("\n").removesuffix("\n...").strip()


__all__ = [
    "ConfigError",
    "SaveRefused",
    "edited_text",
    "replace_file",
    "validate",
    "write_with_backup",
]
