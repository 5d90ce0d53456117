"""A whole inspection mapping, as the console's page holds it, read by the loader's own rules.

The console tries and saves an inspection it edited whole (or a new one, a *draft*): the
mapping goes through :func:`vision_server.inspections.parse_inspection` exactly as an entry of
``inspections:`` in the file does (unknown keys refused, job steps and verdict expressions
parsed, the ROI checked against the image size the camera declares). There is no second
validator: an error names the key path inside the mapping as the file's loader would, e.g.
``steps[2] (name='magnet') -> roi: ...``.

What a request may not choose: a file the server would open outside the configuration's
folder. A template named by a draft must be a relative path that stays inside that folder
(the page trains templates into ``templates/`` there), unless the file already names the very
same path for that inspection (a hand edit the page sends back unchanged).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path, PurePosixPath
from typing import Any

from ..cameras import CameraSettings
from ..inspections import InspectionSpec, parse_inspection
from .document import ConfigError, Node

__all__ = ["MAX_DRAFT_DEPTH", "check_files", "file_keys", "parse_draft"]

MAX_DRAFT_DEPTH = 12
"""How deep a draft's mappings and lists may nest (an inspection nests 4 at most)."""


def parse_draft(
    config: Any,
    *,
    base_dir: Path,
    cameras: Mapping[str, CameraSettings],
    written: Mapping[str, Any] | None = None,
) -> InspectionSpec:
    """The inspection ``config`` describes, validated as the file's loader validates an entry
    of ``inspections:``. ``written``: the inspection as the file has it now (None: a draft),
    whose file paths the draft may keep. Raises ConfigError naming the key path in the
    mapping (no file and no line: it is not in a file yet)."""
    if not isinstance(config, dict):
        raise ConfigError("an inspection is a mapping of its keys")
    _check_depth(config, 0)
    check_files(config, base_dir=base_dir, written=written)
    node = Node(config, (), "", {}, {})
    return parse_inspection(node, base_dir=base_dir, cameras=cameras)


def check_files(
    config: Mapping[str, Any], *, base_dir: Path, written: Mapping[str, Any] | None
) -> None:
    """Refuse a file named by ``config`` outside the configuration's folder ``base_dir``
    (ConfigError naming its key path) unless ``written`` (the inspection as the file has it)
    names that very path there."""
    for path, value in file_keys(config):
        kept = written is not None and _at(written, path) == value
        if not kept:
            _check_inside(path, value, base_dir)


def file_keys(config: Mapping[str, Any]) -> Iterator[tuple[tuple[str | int, ...], Any]]:
    """The key paths and values of the files an inspection mapping names: a presence's
    ``template``, a locate's ``template.image``, an anomaly check's ``model``, and the same
    keys in a job's steps."""
    yield from _files_of(config, ())
    steps = config.get("steps")
    if isinstance(steps, list):
        for index, step in enumerate(steps):
            if isinstance(step, dict):
                yield from _files_of(step, ("steps", index))


def _files_of(
    mapping: Mapping[str, Any], prefix: tuple[str | int, ...]
) -> Iterator[tuple[tuple[str | int, ...], Any]]:
    template = mapping.get("template")
    if isinstance(template, dict):
        if "image" in template:
            yield (*prefix, "template", "image"), template["image"]
    elif template is not None:
        yield (*prefix, "template"), template
    if mapping.get("model") is not None:
        yield (*prefix, "model"), mapping["model"]


def _at(mapping: Any, path: tuple[str | int, ...]) -> Any:
    for part in path:
        if isinstance(part, int):
            if not isinstance(mapping, list) or part >= len(mapping):
                return None
        elif not isinstance(mapping, dict):
            return None
        mapping = mapping[part] if isinstance(part, int) else mapping.get(part)
    return mapping


def _check_inside(path: tuple[str | int, ...], value: Any, base_dir: Path) -> None:
    where = _describe(path)
    if not isinstance(value, str) or not value:
        return  # the loader says what it expected
    pure = PurePosixPath(value.replace("\\", "/"))
    if pure.is_absolute() or value.startswith("~") or ".." in pure.parts or ":" in value:
        raise ConfigError(
            f"{value!r}: a file named from the console must be a relative path inside the "
            "configuration's folder (e.g. templates/part.png); name others in the file by hand",
            path=where,
        )
    resolved = (base_dir / pure).resolve()
    if not resolved.is_relative_to(base_dir.resolve()):
        raise ConfigError(
            f"{value!r} leads outside the configuration's folder (a link?); name it by hand",
            path=where,
        )


def _describe(path: tuple[str | int, ...]) -> str:
    out: list[str] = []
    for part in path:
        if isinstance(part, int) and out:
            out[-1] += f"[{part}]"
        else:
            out.append(str(part))
    return " -> ".join(out)


def _check_depth(value: Any, depth: int) -> None:
    if depth > MAX_DRAFT_DEPTH:
        raise ConfigError(f"the mapping nests deeper than {MAX_DRAFT_DEPTH} levels")
    if isinstance(value, dict):
        for key, inner in value.items():
            if not isinstance(key, str):
                raise ConfigError(f"key {key!r} is not a string")
            _check_depth(inner, depth + 1)
    elif isinstance(value, list):
        for inner in value:
            _check_depth(inner, depth + 1)
