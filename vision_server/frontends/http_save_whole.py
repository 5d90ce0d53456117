"""Saving a whole inspection from the console: replace its mapping in the configuration file,
or append a new one to ``inspections:``.

The file is edited as text through the parsed document's node positions, as
:mod:`.http_save` does for single values, so that everything outside the one inspection stays
byte for byte as written (comments, order, anchors):

1. the mapping is checked: its ``name`` is the inspection's, its keys names, its values
   booleans, finite numbers, strings, nulls, lists and mappings of those, nested at most
   :data:`MAX_DEPTH` deep;
2. it is rendered by this module (never by a YAML emitter's guesses): block YAML at the
   indentation of the entry it replaces (or, in a flow list, one flow mapping), every string
   double-quoted with every character that could be structure escaped, so that no text can
   become YAML structure;
3. an entry written with anchors, aliases or merge keys is refused: its text is shared with
   other places of the file (edit it by hand);
4. the new text must read back as the old document with only this entry replaced (or
   appended), then it is validated by the loader ``serve`` uses and the inspection by the
   rules a try runs, as a save of values is (:func:`.http_save.validate`);
5. the old file is kept through :func:`.http_save.write_version` and the file replaced
   atomically. The caller reloads, and puts the old text back when the reload fails.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from yamlfile import NAME

from ..config import ConfigError, history, parse_document
from . import http_save
from .http_save import (
    KEY_PART,
    AlreadyInvalid,
    BadKey,
    BadValue,
    NotInPlace,
    NotVerified,
    OpenedCamera,
    Saved,
)

MAX_DEPTH = 8
"""How deep a saved mapping's values may nest (a job's step's sub-mapping is 4 deep)."""
INDENT = 2
"""Spaces per nesting level of a mapping this module writes."""


@dataclass(frozen=True)
class SavedWhole:
    """A whole inspection written: the save (old bytes, the history's version) and whether
    it was new."""

    saved: Saved
    created: bool


def save_whole(
    path: Path,
    inspection: str,
    config: Any,
    *,
    opened: Mapping[str, OpenedCamera] | None = None,
    who: str = "console",
    why: str = "",
) -> SavedWhole:
    """Write ``config`` as inspection ``inspection`` of the configuration file ``path`` (a new
    entry at the end of ``inspections:`` when there is none of that name), recorded in the
    file's history as a version by ``who`` for ``why``.
    Raises :class:`~.http_save.SaveRefused` or ConfigError (nothing written), OSError or
    UnicodeError (the file cannot be read or written; nothing left behind)."""
    old = path.read_bytes()
    text = old.decode("utf-8")
    try:
        http_save.validate(text, path)
    except ConfigError as exc:
        raise AlreadyInvalid(
            f"{path.name} is already invalid before inspection {inspection!r} is written (an "
            f"edit made outside the console, not loaded yet): {exc}"
        ) from None
    new, created = replaced_text(text, path.name, inspection, config)
    http_save.validate(new, path, inspection=inspection, opened=opened)
    kind = history.CREATED_INSPECTION if created else history.SAVE
    version = http_save.write_version(path, new, old=old, who=who, why=why, kind=kind)
    return SavedWhole(Saved(path, old, version), created)


def replaced_text(text: str, source: str, inspection: str, config: Any) -> tuple[str, bool]:
    """``text`` with inspection ``inspection``'s entry replaced by ``config`` (appended when
    there is none), verified to read back as exactly that; and whether it was appended.
    Raises :class:`~.http_save.SaveRefused`."""
    where = f"{source}: inspection {inspection!r}"
    check_mapping(where, inspection, config)
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        before = parse_document(text, source=source).data
    except (yaml.YAMLError, ConfigError) as exc:
        raise NotInPlace(f"{source}: the file cannot be read as YAML: {exc}") from None
    if not isinstance(root, yaml.MappingNode):
        raise NotInPlace(f"{source}: the file's top level is not a mapping")
    pair = http_save._pair(root, "inspections")
    items = None if pair is None else pair[1]
    index, item = _find(items, inspection)
    if item is not None:
        _check_unshared(text, where, root, item)
        start, end = item.start_mark.index, http_save._end(text, item)
        if item.flow_style:
            replacement = _flow(config)
        else:
            replacement = _block_mapping(config, item.start_mark.column)
        created = False
    else:
        start, end, replacement = _append(text, root, pair, config)
        created = True
    if "\r\n" in text:  # a file written on Windows keeps its line ends (no text has one)
        replacement = replacement.replace("\n", "\r\n")
    out = text[:start] + replacement + text[end:]
    _verify(out, source, where, before, index, config)
    return out, created


# ----------------------------------------------------------------------------- checks


def check_mapping(where: str, inspection: str, config: Any) -> None:
    """Refuse what cannot be written as the inspection's mapping (SaveRefused naming it)."""
    if not isinstance(config, dict) or not config:
        raise BadValue(f"{where}: config must be the inspection's mapping of keys")
    if config.get("name") != inspection:
        raise BadKey(
            f"{where} -> name: the mapping's name {config.get('name')!r} is not the "
            f"inspection's {inspection!r} (rename by hand)"
        )
    _check_value(where, config, 0)


def _check_value(where: str, value: Any, depth: int) -> None:
    if depth > MAX_DEPTH:
        raise BadValue(f"{where}: nested deeper than {MAX_DEPTH} levels")
    if isinstance(value, dict):
        for key, inner in value.items():
            # A plain name, or a summary value's STEP.VALUE (an output's scale names them).
            if not isinstance(key, str) or not NAME.fullmatch(key):
                raise BadKey(
                    f"{where}: {key!r} is not a key (letters, digits, '_', '.' and '-', at most 64)"
                )
            _check_value(f"{where} -> {key}", inner, depth + 1)
    elif isinstance(value, list):
        for index, inner in enumerate(value):
            _check_value(f"{where}[{index}]", inner, depth + 1)
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise BadValue(f"{where}: {value!r} is not a finite number")
    elif isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:  # a lone surrogate from JSON's \ud800
            raise BadValue(f"{where}: the text is not valid Unicode") from None
        if len(value) > http_save.MAX_TEXT:
            raise BadValue(
                f"{where}: a text of {len(value)} characters, at most {http_save.MAX_TEXT}"
            )
    elif value is not None and not isinstance(value, bool | int):
        raise BadValue(f"{where}: expected a number, a string, a boolean, a list or a mapping")


def _check_unshared(text: str, where: str, root: yaml.Node, item: yaml.MappingNode) -> None:
    """Refuse an entry whose text has an anchor, an alias or a merge key: replacing it would
    change or break the places that share it."""
    counts = http_save._references(root)
    end = http_save._end(text, item)
    for node in http_save._walk(item):
        shared = counts.get(id(node), 0) > 1 or not http_save._inside(node, item)
        merge = isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:merge"
        if shared or merge:
            raise NotInPlace(
                f"{where}: its mapping uses anchors, aliases or merge keys (shared with other "
                "places of the file): it cannot be replaced whole; edit it by hand"
            )
    # The entry's text alone, at its own column (an unused anchor leaves no shared node).
    span = " " * item.start_mark.column + text[item.start_mark.index : end]
    try:
        tokens = list(yaml.scan(span, Loader=yaml.SafeLoader))
    except yaml.YAMLError:
        return  # the walk above has seen its nodes
    if any(isinstance(t, yaml.AnchorToken | yaml.AliasToken) for t in tokens):
        raise NotInPlace(
            f"{where}: its mapping defines an anchor: it cannot be replaced whole; edit it by hand"
        )


# ----------------------------------------------------------------------------- placing


def _find(items: yaml.Node | None, inspection: str) -> tuple[int, yaml.MappingNode | None]:
    """The entry named ``inspection`` and its index; (count of entries, None) when absent."""
    if not isinstance(items, yaml.SequenceNode):
        return 0, None
    for index, item in enumerate(items.value):
        if not isinstance(item, yaml.MappingNode):
            continue
        named = http_save._value_of(item, "name")
        if isinstance(named, yaml.ScalarNode) and named.value == inspection:
            return index, item
    return len(items.value), None


def _append(
    text: str,
    root: yaml.MappingNode,
    pair: tuple[yaml.Node, yaml.Node] | None,
    config: Mapping[str, Any],
) -> tuple[int, int, str]:
    """The edit that adds ``config`` as the last entry of ``inspections:``: (start, end,
    replacement), in the list's own style."""
    if pair is None:
        # No inspections: at all: a new top-level key at the end, at the top level's column.
        column = root.value[0][0].start_mark.column if root.value else 0
        lead = "" if not text or text.endswith("\n") else "\n"
        block = _block_sequence_item(config, column + INDENT, column + 2 * INDENT)
        return len(text), len(text), f"{lead}{' ' * column}inspections:\n{block}\n"
    key_node, items = pair
    if isinstance(items, yaml.ScalarNode):
        if items.value not in ("", "~", "null", "Null", "NULL") or items.tag.endswith(":str"):
            raise NotInPlace("inspections: is not a list; edit it by hand")
        column = key_node.start_mark.column + INDENT
        end = http_save._end(text, items)
        block = _block_sequence_item(config, column, column + INDENT)
        return key_node.end_mark.index, end, ":\n" + block
    if not isinstance(items, yaml.SequenceNode):
        raise NotInPlace("inspections: is not a list; edit it by hand")
    if items.flow_style:
        close = text.rindex("]", items.start_mark.index, items.end_mark.index)
        sep = ", " if items.value else ""
        return close, close, f"{sep}{_flow(config)}"
    first, last = items.value[0], items.value[-1]
    dash = text.rfind("-", 0, first.start_mark.index)
    dash_column = dash - (text.rfind("\n", 0, dash) + 1)
    content = first.start_mark.column if isinstance(first, yaml.CollectionNode) else dash_column
    content = max(content, dash_column + 2)
    after = http_save._end(text, last)
    line_end = text.find("\n", after)
    if line_end < 0:
        line_end = len(text)
    elif line_end > after and text[line_end - 1] == "\r":
        line_end -= 1
    return line_end, line_end, "\n" + _block_sequence_item(config, dash_column, content)


# ----------------------------------------------------------------------------- rendering


def _block_sequence_item(config: Mapping[str, Any], dash_column: int, column: int) -> str:
    """``config`` as one item of a block sequence: its dash at ``dash_column``, its keys at
    ``column``."""
    body = _block_mapping(config, column)
    return " " * dash_column + "-" + " " * (column - dash_column - 1) + body


def _block_mapping(mapping: Mapping[str, Any], column: int) -> str:
    """``mapping`` as block YAML whose keys stand at ``column``; the first line carries no
    indentation (it follows the text before it: a dash, or the start of an entry)."""
    lines = _mapping_lines(mapping, column)
    return "\n".join(lines)[column:]


def _mapping_lines(mapping: Mapping[str, Any], column: int) -> list[str]:
    pad = " " * column
    lines: list[str] = []
    for key, value in mapping.items():
        head = f"{pad}{_key(key)}:"
        if isinstance(value, dict) and value:
            lines.append(head)
            lines.extend(_mapping_lines(value, column + INDENT))
        elif isinstance(value, list) and any(isinstance(v, dict) for v in value):
            lines.append(head)
            for inner in value:
                lines.extend(_sequence_item_lines(inner, column + INDENT))
        else:
            lines.append(f"{head} {_flow(value)}")
    return lines


def _sequence_item_lines(value: Any, dash_column: int) -> list[str]:
    """One item of a block sequence (a mapping in block style, anything else in flow)."""
    if isinstance(value, dict) and value:
        inner = _mapping_lines(value, dash_column + INDENT)
        inner[0] = " " * dash_column + "- " + inner[0][dash_column + INDENT :]
        return inner
    return [" " * dash_column + "- " + _flow(value)]


def _flow(value: Any) -> str:
    """``value`` as flow YAML on one line: strings double-quoted, numbers, booleans and null
    as YAML reads them back."""
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_key(k)}: {_flow(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_flow(v) for v in value) + "]"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return http_save._rendered("", value)
    return _quoted(str(value))


def _quoted(text: str) -> str:
    dumped = yaml.safe_dump(text, default_style='"', width=1 << 30, allow_unicode=True)
    out = dumped.removesuffix("\n").removesuffix("\n...").strip()
    if "\n" in out or "\r" in out:  # safe_dump escapes breaks inside double quotes
        raise BadValue(f"{text[:40]!r} cannot be written on one line")
    return out


def _key(key: str) -> str:
    """A key as written: plain when it is an identifier YAML reads as that text, else
    double-quoted (``"n"``, ``"on"``, ``"gauge.plate_width"``, ``"1e3"``)."""
    plain = KEY_PART.match(key) and key.lower() not in (
        "y", "n", "yes", "no", "on", "off", "true", "false", "null",
    )  # fmt: skip
    return key if plain else _quoted(key)


# ----------------------------------------------------------------------------- verify


def _verify(
    text: str, source: str, where: str, before: Any, index: int, config: Mapping[str, Any]
) -> None:
    """``text`` must read back as ``before`` with entry ``index`` of ``inspections`` being
    ``config`` (or ``config`` appended there)."""
    try:
        after = parse_document(text, source=source).data
    except ConfigError as exc:
        raise NotVerified(
            f"{where}: the edited file would not read back ({exc}); nothing was written: edit "
            "it by hand"
        ) from None
    intended = dict(before) if isinstance(before, dict) else {}
    items = list(intended.get("inspections") or [])
    if index < len(items):
        items[index] = dict(config)
    else:
        items.append(dict(config))
    intended["inspections"] = items
    wrong = http_save._difference(intended, after, ())
    if wrong is not None:
        shown = " -> ".join(str(p) for p in wrong) or "the document"
        raise NotVerified(
            f"{where}: the edit would change {shown} otherwise than intended; nothing was "
            "written: edit it by hand"
        )


__all__ = ["MAX_DEPTH", "SavedWhole", "check_mapping", "replaced_text", "save_whole"]
