"""Writing solved intrinsics into the vision server's configuration file.

The camera's ``intrinsics:`` entry is replaced in place (or added under the camera; into a
camera written as a one-line mapping, inside it), as one flow mapping, with a comment line
above it that says when, from which board and how well it was calibrated. The rest of the
file, its comments and layout included, is kept as it was: the file is edited as text at the
places YAML's parser locates, never re-dumped.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from geometry import CameraIntrinsics

__all__ = [
    "MARKER",
    "file_hash",
    "intrinsics_text",
    "replace_intrinsics",
    "served_mismatch",
    "write_intrinsics",
]

MARKER = "# intrinsics calibrated"  # the comment line this module writes (and replaces)


def intrinsics_text(intrinsics: CameraIntrinsics) -> str:
    """The flow mapping of ``intrinsics`` as the configuration writes it (pixels)."""
    k = intrinsics
    dist = ", ".join(f"{d:.7g}" for d in k.dist)
    return (
        f"{{width: {k.width}, height: {k.height}, fx: {k.fx:.3f}, fy: {k.fy:.3f}, "
        f"cx: {k.cx:.3f}, cy: {k.cy:.3f}, distortion: [{dist}]}}"
    )


def _mapping_item(node: yaml.Node, key: str) -> tuple[yaml.ScalarNode, yaml.Node] | None:
    if not isinstance(node, yaml.MappingNode):
        return None
    for k, v in node.value:
        if isinstance(k, yaml.ScalarNode) and k.value == key:
            return k, v
    return None


def replace_intrinsics(text: str, camera: str, intrinsics: CameraIntrinsics, note: str) -> str:
    """``text`` (a server configuration) with camera ``camera``'s intrinsics set; ``note`` goes
    into the comment line above them. Raises ``ValueError`` when the file has no such camera
    or is not YAML."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise ValueError(f"the configuration is not YAML: {exc}") from None
    cameras = _mapping_item(root, "cameras") if root is not None else None
    entry = _mapping_item(cameras[1], camera) if cameras is not None else None
    if entry is None or not isinstance(entry[1], yaml.MappingNode):
        raise ValueError(f"the configuration has no camera {camera!r} under cameras:")
    camera_node = entry[1]
    value = intrinsics_text(intrinsics)
    existing = _mapping_item(camera_node, "intrinsics")
    if getattr(camera_node, "flow_style", False):
        return _replace_in_flow(text, entry[0], camera_node, existing, value, note)
    lines = text.splitlines(keepends=True)
    if existing is not None:
        key, node = existing
        first = key.start_mark.line
        indent = " " * key.start_mark.column
        # A flow mapping (or a scalar) ends on its last line; a block one where the next key
        # (or the end of the file) is.
        inline = bool(getattr(node, "flow_style", False)) or isinstance(node, yaml.ScalarNode)
        last = node.end_mark.line if inline and node.end_mark.column else node.end_mark.line - 1
        while last > first and not lines[last].strip():
            last -= 1
        del lines[first : last + 1]
    else:
        first_key, last_value = camera_node.value[0][0], camera_node.value[-1][1]
        indent = " " * first_key.start_mark.column
        # Right after the camera's last entry (not after comments that follow it).
        first = last_value.end_mark.line + (1 if last_value.end_mark.column else 0)
        while first > first_key.start_mark.line + 1 and not lines[first - 1].strip():
            first -= 1
    if first > 0 and lines[first - 1].strip().startswith(MARKER):
        first -= 1
        del lines[first]
    if lines and first == len(lines) and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    head, _, dist = value.partition(" distortion: ")
    lines[first:first] = [
        f"{indent}{MARKER} {note}\n",
        f"{indent}intrinsics: {head}\n",
        f"{indent}{' ' * len('intrinsics: {')}distortion: {dist}\n",
    ]
    return "".join(lines)


def _replace_in_flow(
    text: str,
    camera_key: yaml.Node,
    camera_node: yaml.Node,
    existing: tuple[yaml.ScalarNode, yaml.Node] | None,
    value: str,
    note: str,
) -> str:
    """A camera written as a one-line mapping (``name: {source: ...}``): its intrinsics are
    replaced, or join it before its closing brace; the note goes above the camera's line."""
    if existing is not None:
        start, end = existing[1].start_mark.index, existing[1].end_mark.index
    else:
        start = end = camera_node.end_mark.index - 1
        value = f", intrinsics: {value}"
    lines = (text[:start] + value + text[end:]).splitlines(keepends=True)
    line = camera_key.start_mark.line
    if line > 0 and lines[line - 1].strip().startswith(MARKER):
        line -= 1
        del lines[line]
    lines.insert(line, f"{' ' * camera_key.start_mark.column}{MARKER} {note}\n")
    return "".join(lines)


def write_intrinsics(path: Path, camera: str, intrinsics: CameraIntrinsics, note: str) -> Path:
    """Set the camera's intrinsics in the file at ``path`` (atomically: a temporary file
    then a rename); returns the backup of the previous file (``<name>.bak``)."""
    text = path.read_text(encoding="utf-8")
    new = replace_intrinsics(text, camera, intrinsics, note)
    backup = path.with_name(path.name + ".bak")
    backup.write_text(text, encoding="utf-8")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(new, encoding="utf-8")
    os.replace(tmp, path)
    return backup


def file_hash(path: Path) -> str:
    """The configuration hash the reference server reports for the file at ``path`` (the
    first 16 hex digits of the SHA-256 of its UTF-8 text): for messages, never a verdict."""
    return hashlib.sha256(path.read_text(encoding="utf-8").encode("utf-8")).hexdigest()[:16]


def served_mismatch(
    cameras: Sequence[Mapping[str, Any]], camera: str, intrinsics: CameraIntrinsics
) -> str | None:
    """How the server's camera descriptors (RELOADED's or WELCOME's ``cameras``, SPEC §5.2)
    disagree with ``intrinsics`` written for ``camera`` (pixels, to the 3 decimals the file
    holds); None when the server serves them."""
    served = next((c for c in cameras if c.get("name") == camera), None)
    if served is None:
        names = ", ".join(str(c.get("name")) for c in cameras) or "none"
        return f"the server has no camera {camera!r} (its cameras: {names})"
    got = served.get("intrinsics")
    if not isinstance(got, Mapping):
        return f"the server's camera {camera!r} reports no intrinsics"
    wanted = {
        "width": intrinsics.width,
        "height": intrinsics.height,
        "fx": intrinsics.fx,
        "fy": intrinsics.fy,
        "cx": intrinsics.cx,
        "cy": intrinsics.cy,
    }
    for key, value in wanted.items():
        other = got.get(key)
        # The file holds 3 decimals of the focal lengths and the principal point.
        if not isinstance(other, int | float) or not math.isclose(other, value, abs_tol=1e-3):
            return f"the server's camera {camera!r} has {key} {other}, the file {value:.3f}"
    dist = list(got.get("dist") or [])
    if len(dist) < 5 or any(
        not math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-9)
        for a, b in zip(dist, intrinsics.dist, strict=False)
    ):
        written = list(intrinsics.dist)
        return f"the server's camera {camera!r} has distortion {dist}, the file {written}"
    return None
