"""Saving an inspection's tuned keys from the console into the configuration file.

The save changes the configuration through its YAML model, written in place so that comments,
order and anchors elsewhere stay as the integrator wrote them:

1. every key is checked (dotted names of plain identifiers, none fixed by the configuration:
   :data:`~vision_server.config.FIXED_BY_THE_CONFIGURATION`) and every value (a boolean, a
   number, a string, or a flat list of them);
2. the inspection's mapping is located through the parsed document's node positions, and each
   value is written there as one properly quoted YAML scalar or flow list (a string is always
   double-quoted, so no text can become structure); nothing shared with another entry through
   an anchor is edited;
3. the new text is parsed again and must equal the intended model (the old document with only
   this inspection's given values set), then it is validated by the loader ``serve`` uses
   (:func:`vision_server.config.parse_config`) and the inspection by the rules a try runs
   (:class:`vision_server.config.Tuner`), with the image size each running camera declares;
4. the new text is recorded as a version of the file's history (who, when, why, which
   inspections changed: :mod:`vision_server.config.history`, ``NAME.history/`` beside it),
   then the file is replaced atomically (:func:`write_version`, the one place the console
   writes the configuration file).

Anything else is refused with a :class:`SaveRefused` subclass naming the cause, or the
validator's :class:`~vision_server.config.ConfigError`; nothing is written then.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from ..config import (
    FIXED_BY_THE_CONFIGURATION,
    CellConfig,
    ConfigError,
    Tuner,
    files,
    history,
    parse_config,
    parse_document,
)

MAX_TEXT = 4096
"""The longest text a save writes as one value (a description, a pattern), characters."""
MAX_CONFIG_BYTES = 1 << 20
"""The largest configuration file the console writes, bytes: a cell's file is some kilobytes;
without a bound, saves of long texts grew it to megabytes, each save slower than the last and
the history's byte bound dropping the versions an audit needs."""

KEY_PART = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}\Z")
"""One part of a key (``circle.min_radius_px`` has two): a plain identifier, as every key of
an inspection is."""


class SaveRefused(ValueError):
    """The edit cannot be made; the message names the file, the inspection, the key and the
    cause. ``cause`` says which check refused it (each subclass has its own)."""

    cause = "refused"


class BadKey(SaveRefused):
    """A key that is not a dotted name of plain identifiers."""

    cause = "key"


class FixedKey(SaveRefused):
    """A key fixed by the configuration (``number``, ``type``, ``camera``, ...)."""

    cause = "fixed"


class BadValue(SaveRefused):
    """A value that is not a boolean, a finite number, a string or a flat list of them."""

    cause = "value"


class NotInPlace(SaveRefused):
    """The file's shape does not allow the edit in place (no such inspection, a nested key
    whose parent is not a mapping written in the inspection, a value shared through an
    anchor): it is edited by hand."""

    cause = "structure"


class NotVerified(SaveRefused):
    """The edited text does not read back as the intended model (a safeguard: nothing is
    written)."""

    cause = "verify"


class AlreadyInvalid(SaveRefused):
    """The file is invalid before the edit (a hand edit not loaded yet)."""

    cause = "invalid"


@dataclass(frozen=True)
class OpenedCamera:
    """A running camera as the save sees it: the settings it was built from and the
    intrinsics it declares once open (a simulated camera's come from its scene)."""

    settings: Any
    intrinsics: Any


@dataclass(frozen=True)
class Saved:
    """A save written: the file's old bytes and the history's version of the new text."""

    path: Path
    old: bytes
    version: history.Version


# ----------------------------------------------------------------------------- the save


def save(
    path: Path,
    inspection: str,
    options: Mapping[str, Any],
    *,
    opened: Mapping[str, OpenedCamera] | None = None,
    who: str = "console",
    why: str = "",
) -> Saved:
    """Set ``options`` (dotted keys for nested ones) of inspection ``inspection`` in the
    configuration file ``path``, recorded in its history as ``who``'s save for ``why``.
    Raises :class:`SaveRefused` or ConfigError (nothing written), OSError or UnicodeError (the
    file cannot be read or written; nothing left behind). ``opened``: the running cameras,
    whose declared image sizes the inspection's ROI must fit as a try's must."""
    old = path.read_bytes()
    text = old.decode("utf-8")
    try:
        # The file as it is now first: when a hand edit (not loaded yet) made it invalid, the
        # refusal must say that the fault is there, not in the values being saved.
        validate(text, path)
    except ConfigError as exc:
        raise AlreadyInvalid(
            f"{path.name} is already invalid before {inspection!r}'s values are written (an "
            f"edit made outside the console, not loaded yet; {inspection!r}'s values are not "
            f"the invalid part): {exc}"
        ) from None
    new = edited_text(text, path.name, inspection, options)
    validate(new, path, inspection=inspection, opened=opened)
    version = write_version(path, new, old=old, who=who, why=why)
    return Saved(path, old, version)


def undo(saved: Saved) -> None:
    """Put the old text back (a reload refused what was saved) and drop the save's version
    from the history: the file's history ends again with the text it has."""
    files.replace_file(saved.path, saved.old)
    history.history_of(saved.path).drop(saved.version.number)


def edited_text(text: str, source: str, inspection: str, options: Mapping[str, Any]) -> str:
    """``text`` with the keys ``options`` (dotted for nested ones: ``circle.min_radius_px``)
    of inspection ``inspection`` set to their values, verified to read back as exactly that
    change. Raises :class:`SaveRefused`."""
    if not options:
        raise BadKey(f"{source}: inspection {inspection!r}: no values to save")
    for key, value in options.items():
        _check_option(source, inspection, key, value)
    for key in options:
        parts = key.split(".")
        outer = next(
            (h for i in range(1, len(parts)) if (h := ".".join(parts[:i])) in options), None
        )
        if outer is not None:
            raise BadKey(
                f"{source}: inspection {inspection!r}: both {outer} and {key} are given; give "
                "one of them"
            )
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        before = parse_document(text, source=source).data
    except (yaml.YAMLError, ConfigError) as exc:
        raise NotInPlace(f"{source}: the file cannot be read as YAML: {exc}") from None
    index, item = _inspection_node(root, source, inspection)
    counts = _references(root)
    edits: list[tuple[int, int, str]] = []
    for key, value in options.items():
        parts = key.split(".")
        where = f"{source}: inspection {inspection!r} -> {key}"
        node = item
        for part in parts[:-1]:
            child = _value_of(node, part)
            if not isinstance(child, yaml.MappingNode) or not _inside(child, item):
                raise NotInPlace(
                    f"{where}: {part!r} is not a mapping written in the inspection; edit it by hand"
                )
            node = child
        if counts.get(id(node), 0) > 1:
            raise NotInPlace(
                f"{where}: it is in a mapping shared with other entries through an anchor; "
                "edit it by hand"
            )
        edits.append(_edit(text, where, node, parts[-1], _rendered(where, value), item, counts))
    spans = sorted(edits, key=lambda e: (e[0], e[1]))
    for (_, end, _), (start, _, _) in zip(spans, spans[1:], strict=False):
        if start < end:
            raise NotInPlace(f"{source}: inspection {inspection!r}: two keys edit one value")
    out = text
    for start, end, replacement in reversed(spans):
        out = out[:start] + replacement + out[end:]
    _verify(out, source, inspection, before, index, options)
    return out


def validate(
    text: str,
    path: Path,
    *,
    inspection: str | None = None,
    opened: Mapping[str, OpenedCamera] | None = None,
) -> CellConfig:
    """The configuration ``text`` (to be saved as ``path``) as ``serve`` would load it, and
    with ``inspection`` also that inspection as a try checks it (the :class:`Tuner`), with the
    image size every camera in ``opened`` declares (a camera whose configuration does not say
    its size, e.g. a simulated one, declares it once open). Raises ConfigError naming file,
    line and key path."""
    root = parse_document(text, source=path.name)
    config = parse_config(root, text=text, base_dir=path.resolve().parent, source=path)
    if inspection is None or config.tune is None:
        return config
    cameras = declared_cameras(config.cameras, opened or {})
    tuner = Tuner(config.tune.written, config.base_dir, cameras)
    try:
        tuner(inspection, {})
    except ValueError as exc:  # ConfigError
        # The Tuner names the key as a request's option ("options -> roi"); the save names it
        # in the file, with its line.
        nodes = parse_document(text, source=path.name).items("inspections")
        node = next(n for n in nodes if n.data.get("name") == inspection)
        where = getattr(exc, "path", "").removeprefix("options").removeprefix(" -> ")
        raise ConfigError(
            getattr(exc, "reason", str(exc)),
            source=path.name,
            line=node.line(where.split(" -> ")[0] or None),
            path=node.describe() + (f" -> {where}" if where else ""),
        ) from None
    return config


def declared_cameras(
    cameras: Mapping[str, Any], opened: Mapping[str, OpenedCamera]
) -> dict[str, Any]:
    """``cameras`` (settings by name) where a camera whose settings declare no image size
    takes the intrinsics its running camera declares, when it runs with these same settings
    (a hand edit of the camera: its new size is not known before it opens)."""
    out = dict(cameras)
    for name, settings in cameras.items():
        running = opened.get(name)
        if running is None or running.intrinsics is None or running.settings != settings:
            continue
        if getattr(settings, "intrinsics", False) is not None:
            continue  # declared already, or settings without intrinsics
        if isinstance(getattr(settings, "width", None), int):
            continue  # declared by its width and height
        with contextlib.suppress(TypeError, ValueError):
            out[name] = dataclasses.replace(settings, intrinsics=running.intrinsics)
    return out


def opened_cameras(catalog: Any) -> dict[str, OpenedCamera]:
    """The cameras a served catalog runs, with the settings its configuration gave them."""
    tune = getattr(catalog, "tune", None)
    settings = getattr(tune, "cameras", None)
    if not isinstance(settings, Mapping):
        return {}
    return {
        name: OpenedCamera(settings[name], camera.intrinsics)
        for name, camera in catalog.cameras.items()
        if name in settings
    }


# ----------------------------------------------------------------------------- files


def write_version(
    path: Path,
    text: str,
    *,
    old: bytes | None = None,
    who: str = "console",
    why: str = "",
    kind: str = history.SAVE,
    reverted_to: int | None = None,
) -> history.Version:
    """Replace the configuration file ``path`` with ``text`` and record it in the file's
    history as a version of ``kind`` made by ``who`` for ``why`` (``reverted_to``: the
    version a revert restores). ``old``: the file's bytes as read (read now when None).

    The one place the console writes the configuration file
    (:func:`~vision_server.config.history.write_with_history`), after checking its size.
    Returns the new version (give it to :func:`undo` through :class:`Saved` when the server
    then refuses the text). Raises OSError (nothing changed but perhaps the catch-up)."""
    data = text.encode("utf-8")
    if len(data) > MAX_CONFIG_BYTES:
        raise SaveRefused(
            f"{path.name}: the new text has {len(data)} bytes, the console writes at most "
            f"{MAX_CONFIG_BYTES} (long texts belong in files beside it, not in the configuration)"
        )
    return history.write_with_history(
        path, data, old=old, who=who, why=why, kind=kind, reverted_to=reverted_to
    )


# ----------------------------------------------------------------------------- checks


def _check_option(source: str, inspection: str, key: Any, value: Any) -> None:
    if not isinstance(key, str) or not all(KEY_PART.match(part) for part in key.split(".")):
        raise BadKey(
            f"{source}: inspection {inspection!r}: {key!r} is not a key (names of letters, "
            "digits and underscores, dotted for a nested one: circle.min_radius_px)"
        )
    where = f"{source}: inspection {inspection!r} -> {key}"
    if key.split(".")[0] in FIXED_BY_THE_CONFIGURATION:
        fixed = ", ".join(sorted(FIXED_BY_THE_CONFIGURATION))
        raise FixedKey(f"{where}: cannot be changed from the console ({fixed}: edit the file)")
    if not _plain(value):
        raise BadValue(
            f"{where}: expected a number, a string (valid Unicode, at most {MAX_TEXT} "
            "characters), a boolean or a list of them"
        )


def _plain(value: Any) -> bool:
    if isinstance(value, bool | int):
        return True
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:  # a lone surrogate from JSON's \ud800
            return False
        return len(value) <= MAX_TEXT
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, list):
        return all(not isinstance(v, list) and _plain(v) for v in value)
    return False


def _rendered(where: str, value: Any) -> str:
    """``value`` as YAML on one line: a string double-quoted (every character that could be
    structure or a line break escaped), a number or boolean as YAML reads it back, a list in
    flow style of those."""
    if isinstance(value, list):
        return "[" + ", ".join(_rendered(where, v) for v in value) + "]"
    if isinstance(value, str):
        dumped = yaml.safe_dump(value, default_style='"', width=1 << 30, allow_unicode=True)
    else:
        dumped = yaml.safe_dump(value, width=1 << 30)
    out = dumped.removesuffix("\n").removesuffix("\n...").strip()
    if not out or "\n" in out or "\r" in out:
        raise BadValue(f"{where}: {value!r} cannot be written on one line")
    return out


def _verify(
    text: str,
    source: str,
    inspection: str,
    before: dict[Any, Any],
    index: int,
    options: Mapping[str, Any],
) -> None:
    """``text`` must read back as ``before`` with only inspection ``index``'s given keys set."""
    try:
        after = parse_document(text, source=source).data
    except ConfigError as exc:
        raise NotVerified(
            f"{source}: inspection {inspection!r}: the edited file would not read back ({exc}); "
            "nothing was written: edit it by hand"
        ) from None
    intended = dict(before)
    items = list(intended["inspections"])
    item = dict(items[index])
    for key, value in options.items():
        *heads, last = key.split(".")
        mapping = item
        for head in heads:
            mapping[head] = dict(mapping[head])
            mapping = mapping[head]
        mapping[last] = value
    items[index] = item
    intended["inspections"] = items
    wrong = _difference(intended, after, ())
    if wrong is not None:
        shown = " -> ".join(str(p) for p in wrong) or "the document"
        raise NotVerified(
            f"{source}: inspection {inspection!r}: the edit would change {shown} otherwise than "
            "intended; nothing was written: edit it by hand"
        )


def _difference(a: Any, b: Any, path: tuple[Any, ...]) -> tuple[Any, ...] | None:
    """The first key path where ``a`` and ``b`` differ (types too: ``true`` is not ``1``)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return (*path, sorted(set(a) ^ set(b), key=str)[0])
        for key in a:
            found = _difference(a[key], b[key], (*path, key))
            if found is not None:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            found = _difference(x, y, (*path, i))
            if found is not None:
                return found
        return None
    if type(a) is not type(b) or a != b:
        return path
    return None


# ----------------------------------------------------------------------------- nodes


def _inspection_node(root: Any, source: str, name: str) -> tuple[int, yaml.MappingNode]:
    inspections = _value_of(root, "inspections") if isinstance(root, yaml.MappingNode) else None
    if not isinstance(inspections, yaml.SequenceNode):
        raise NotInPlace(f"{source}: the file has no list of inspections")
    for index, item in enumerate(inspections.value):
        if not isinstance(item, yaml.MappingNode):
            continue
        named = _value_of(item, "name")
        if isinstance(named, yaml.ScalarNode) and named.value == name:
            return index, item
    raise NotInPlace(f"{source}: the file has no inspection named {name!r}")


def _pair(node: yaml.MappingNode, key: str) -> tuple[yaml.Node, yaml.Node] | None:
    """The (key, value) nodes of ``key`` written in ``node`` (not brought in by ``<<:``)."""
    for key_node, value_node in node.value:
        if (
            isinstance(key_node, yaml.ScalarNode)
            and key_node.tag != "tag:yaml.org,2002:merge"
            and key_node.value == key
        ):
            return key_node, value_node
    return None


def _value_of(node: yaml.MappingNode, key: str) -> yaml.Node | None:
    pair = _pair(node, key)
    return None if pair is None else pair[1]


def _inside(node: yaml.Node, item: yaml.Node) -> bool:
    """Whether ``node`` is written within ``item`` (not an alias of an anchor elsewhere)."""
    return item.start_mark.index <= node.start_mark.index < item.end_mark.index


def _walk(node: yaml.Node) -> Iterator[yaml.Node]:
    """``node`` and every node below it, each once."""
    seen: set[int] = set()
    stack = [node]
    while stack:
        current = stack.pop()
        if id(current) in seen:
            continue
        seen.add(id(current))
        yield current
        if isinstance(current, yaml.SequenceNode):
            stack.extend(current.value)
        elif isinstance(current, yaml.MappingNode):
            for key_node, value_node in current.value:
                stack.extend((key_node, value_node))


def _references(root: yaml.Node | None) -> dict[int, int]:
    """How many places of the document hold each node (by id): more than one is an anchor
    with its aliases."""
    counts: dict[int, int] = {}
    if root is None:
        return counts
    seen: set[int] = set()
    stack = [root]
    while stack:
        current = stack.pop()
        counts[id(current)] = counts.get(id(current), 0) + 1
        if id(current) in seen:
            continue  # an alias: counted, its inside already walked
        seen.add(id(current))
        if isinstance(current, yaml.SequenceNode):
            stack.extend(current.value)
        elif isinstance(current, yaml.MappingNode):
            for key_node, value_node in current.value:
                stack.extend((key_node, value_node))
    return counts


def _end(text: str, node: yaml.Node) -> int:
    """Where ``node``'s own text ends (a block collection's or block scalar's end mark also
    takes the blank lines and comments after it)."""
    if isinstance(node, yaml.ScalarNode):
        if node.style in ("|", ">"):
            span = text[node.start_mark.index : node.end_mark.index]
            return node.start_mark.index + len(span.rstrip(" \t\r\n"))
        return node.end_mark.index
    if getattr(node, "flow_style", False) or not node.value:
        return node.end_mark.index
    last = node.value[-1]
    return _end(text, last[1] if isinstance(node, yaml.MappingNode) else last)


def _edit(
    text: str,
    where: str,
    node: yaml.MappingNode,
    key: str,
    rendered: str,
    item: yaml.MappingNode,
    counts: Mapping[int, int],
) -> tuple[int, int, str]:
    """The edit that makes ``key`` of ``node`` hold ``rendered``: (start, end, replacement)."""
    pair = _pair(node, key)
    if pair is not None:
        key_node, current = pair
        if not _inside(current, item) or any(counts.get(id(n), 0) > 1 for n in _walk(current)):
            raise NotInPlace(
                f"{where}: its value is shared with other entries through an anchor; edit it "
                "by hand"
            )
        start, end = current.start_mark.index, _end(text, current)
        block = isinstance(current, yaml.CollectionNode) and not current.flow_style
        if block:
            # A block list or mapping starts on the next line: the flow value goes right
            # after the key's colon instead, if nothing but spaces stands between them.
            between = text[key_node.end_mark.index : start]
            if between.strip() != ":":
                raise NotInPlace(
                    f"{where}: a comment or tag stands before its value; edit it by hand"
                )
            return key_node.end_mark.index, end, f": {rendered}"
        return start, end, rendered
    if node.flow_style:
        # "{a: 1, b: 2}": add ", key: value" before the closing brace.
        close = text.rindex("}", node.start_mark.index, node.end_mark.index)
        sep = ", " if node.value else ""
        return close, close, f"{sep}{key}: {rendered}"
    if not node.value:
        raise NotInPlace(f"{where}: edit it by hand")
    # After the mapping's last pair written here (a merged or aliased value is written
    # elsewhere: its key's line then), at the indentation of its keys.
    last_key, last_value = node.value[-1]
    after = _end(text, last_value) if _inside(last_value, item) else last_key.end_mark.index
    line_end = text.find("\n", after)
    if line_end < 0:
        line_end = len(text)
    indent = " " * node.value[0][0].start_mark.column
    return line_end, line_end, f"\n{indent}{key}: {rendered}"


__all__ = [
    "AlreadyInvalid",
    "BadKey",
    "BadValue",
    "ConfigError",
    "FixedKey",
    "NotInPlace",
    "NotVerified",
    "OpenedCamera",
    "SaveRefused",
    "Saved",
    "declared_cameras",
    "edited_text",
    "opened_cameras",
    "save",
    "undo",
    "validate",
    "write_version",
]
