"""The teach store: taught skill records in one YAML file, readable and diffable.

Format (schema version 2)::

    format: cellvision-taught
    schema_version: 2
    records:
      - skill: place                  # the skill's name
        name: bin_l2                  # the record's name, unique per skill
        revision: 3                   # 1 when first taught, +1 on every re-teach
        frame: base                   # "base" or a calibrated frame, e.g. "qr:station-1"
        taught_at: "2024-05-01T10:00:00Z"
        notes: ""
        params:                       # the skill's parameters, metres and radians
          pose: {xyz: [0.68, 0.3, 0.1], rpy: [3.14159265, 0.0, 0.0]}
          approach_m: 0.1

Older files are upgraded when read, one version at a time (:data:`UPGRADES`: a function from
version N to N+1 for every N below :data:`SCHEMA_VERSION`); the next write saves the current
version. Version 1 (``version: 1``, ``skills: {name: {skill, params, frame?}}``, poses as 4x4
nested lists) is the only older one.

Files are read through the project's one YAML reader (:mod:`yamlfile`: safe loading only,
duplicate keys refused) and written atomically (a temporary file in the same directory, then
``os.replace``), so a reader sees the old or the new file, never half of one. Errors name the
file, the line, the record and the key (``t.yaml:7 records[0] (place/a) -> revision: ...``); in a
file of an older version, the line of the record as it is written there.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, cast

import yaml

from yamlfile import DocumentError, Key, Node, integer, kind, one_of, parse_document, string

from .skills.record import TaughtRecord, pose_to_yaml

__all__ = [
    "FORMAT",
    "SCHEMA_VERSION",
    "UPGRADES",
    "TeachStore",
    "TeachStoreError",
    "UnknownRecord",
]

FORMAT = "cellvision-taught"
SCHEMA_VERSION = 2


class TeachStoreError(DocumentError):
    """A teach store file that cannot be read or written; the message names file, line, record
    and key."""


class UnknownRecord(TeachStoreError, LookupError):
    """No record of that name."""


# --- upgrades -----------------------------------------------------------------------------


def _is_matrix(value: Any) -> bool:
    return (
        isinstance(value, list)
        and len(value) == 4
        and all(isinstance(row, list) and len(row) == 4 for row in value)
    )


def _upgrade_1_to_2(doc: dict[str, Any]) -> dict[str, Any]:
    """v1: ``skills`` mapping name → {skill, params, frame?, notes?}, poses as 4x4 lists.
    v2: ``records`` list with revision, frame, taught_at; poses as {xyz, rpy}."""
    records = []
    skills = doc.get("skills") or {}
    if not isinstance(skills, dict):
        raise TeachStoreError("key 'skills': expected a mapping of record names (version 1)")
    for name, entry in skills.items():
        if not isinstance(entry, dict):
            raise TeachStoreError(f"skills.{name}: expected a mapping (version 1)")
        params = {
            k: pose_to_yaml(v) if _is_matrix(v) else v
            for k, v in dict(entry.get("params") or {}).items()
        }
        records.append(
            {
                "skill": entry.get("skill"),
                "name": str(name),
                "revision": 1,
                "frame": entry.get("frame", "base"),
                "taught_at": "",
                "notes": entry.get("notes", ""),
                "params": params,
            }
        )
    return {"format": FORMAT, "schema_version": 2, "records": records}


UPGRADES: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {1: _upgrade_1_to_2}
"""UPGRADES[n] turns a version-n document into a version-(n+1) one."""


def _schema_version(doc: Mapping[str, Any]) -> int:
    version = doc.get("schema_version", doc.get("version"))
    if isinstance(version, bool) or not isinstance(version, int):
        raise TeachStoreError(f"key 'schema_version': expected an integer, got {version!r}")
    return version


def upgrade(doc: dict[str, Any]) -> tuple[dict[str, Any], int]:
    """Bring a document to :data:`SCHEMA_VERSION`; returns it and the version it had."""
    original = version = _schema_version(doc)
    if version > SCHEMA_VERSION:
        raise TeachStoreError(
            f"schema_version {version} is newer than this program reads ({SCHEMA_VERSION}); "
            f"update cellvision"
        )
    while version < SCHEMA_VERSION:
        step = UPGRADES.get(version)
        if step is None:
            raise TeachStoreError(f"no upgrade from schema_version {version}")
        doc = step(doc)
        version += 1
    return doc, original


# --- reading ------------------------------------------------------------------------------


class _StoreNode(Node):
    """A mapping of a teach store file; errors are TeachStoreErrors."""

    error_type = TeachStoreError

    def error(self, message: str, key: Key | None = None) -> TeachStoreError:
        return cast(TeachStoreError, super().error(message, key))


def _version_key(root: _StoreNode) -> str:
    return "schema_version" if "schema_version" in root or "version" not in root else "version"


def _upgraded(root: _StoreNode) -> tuple[_StoreNode, int]:
    """The document at :data:`SCHEMA_VERSION` and the version it was written in. An upgraded
    document's records keep the lines their entries are written on (version 1: under
    ``skills:``), so that its errors still point into the file."""
    key = _version_key(root)
    version = root.take(key, integer)
    if version > SCHEMA_VERSION:
        raise root.error(
            f"schema_version {version} is newer than this program reads ({SCHEMA_VERSION}); "
            f"update cellvision",
            key,
        )
    if version == SCHEMA_VERSION:
        return root, version
    lines: dict[tuple[Key, ...], int] = {}
    if version == 1:
        skills = root.sub("skills")
        for index, (name, entry) in enumerate(skills.data.items()):
            if not isinstance(entry, dict):
                raise skills.error(f"expected a mapping, got {kind(entry)}", str(name))
            line = skills.line(str(name))
            if line is not None:
                lines[("records", index)] = line
    try:
        doc, _ = upgrade(dict(root.data))
    except TeachStoreError as exc:
        raise root.error(str(exc)) from None
    return _StoreNode(doc, (), root.source, lines, {}), version


def _positive_int(value: Any) -> int:
    out = integer(value)
    if out < 1:
        raise ValueError(f"expected an integer >= 1, got {value!r}")
    return out


def _params(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ValueError(f"expected a mapping of parameter names, got {kind(value)}")
    return value


def _record(node: _StoreNode) -> TaughtRecord:
    node.label(f"{node.data.get('skill')}/{node.data.get('name')}")
    record = TaughtRecord(
        skill=node.take("skill", string),
        name=node.take("name", string),
        params=node.take("params", _params, {}),
        frame=node.take("frame", _text, "base") or "base",
        revision=node.take("revision", _positive_int, 1),
        taught_at=str(node.take("taught_at", _any, "")),
        notes=node.take("notes", _text, ""),
    )
    node.finish()
    return record


def _any(value: Any) -> Any:
    return value


def _text(value: Any) -> str:
    if not isinstance(value, str):
        raise ValueError(f"expected a string, got {kind(value)}")
    return value


class TeachStore:
    """Taught records in the YAML file ``path`` (created on the first :meth:`put`).

    Every read re-reads the file, so several programs (the CLI, a task runner) can share it.
    ``upgraded_from``: the schema version the last read file had, if older than the current.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.upgraded_from: int | None = None

    def _error(self, message: str) -> TeachStoreError:
        return TeachStoreError(message, source=str(self.path))

    def _read(self) -> list[TaughtRecord]:
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return []
        except (OSError, UnicodeDecodeError) as exc:
            raise self._error(f"cannot read: {getattr(exc, 'strerror', None) or exc}") from None
        root = parse_document(text, source=str(self.path), node_type=_StoreNode)
        if not root.data:
            return []  # an empty file: nothing taught yet
        root, version = _upgraded(root)
        self.upgraded_from = version if version < SCHEMA_VERSION else None
        root.take("format", one_of(FORMAT))
        root.take("schema_version", integer)
        nodes = root.items("records")
        root.finish()
        records: list[TaughtRecord] = []
        first: dict[str, int] = {}
        for index, node in enumerate(nodes):
            record = _record(node)
            if record.key in first:
                where = f"records[{first[record.key]}]"
                raise node.error(f"record {record.key} appears twice (first as {where})")
            first[record.key] = index
            records.append(record)
        return records

    def _write(self, records: list[TaughtRecord]) -> None:
        doc = {
            "format": FORMAT,
            "schema_version": SCHEMA_VERSION,
            "records": [r.to_dict() for r in sorted(records, key=lambda r: (r.skill, r.name))],
        }
        text = (
            "# cellvision taught skills (robot-client teach); metres, radians\n"
            + yaml.safe_dump(
                doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=100
            )
        )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise
        self.upgraded_from = None

    # --- public ---------------------------------------------------------------------------
    def records(self, skill: str | None = None) -> list[TaughtRecord]:
        return [r for r in self._read() if skill is None or r.skill == skill]

    def __iter__(self) -> Iterator[TaughtRecord]:
        return iter(self.records())

    def get(self, skill: str, name: str) -> TaughtRecord:
        for r in self._read():
            if r.skill == skill and r.name == name:
                return r
        known = ", ".join(r.name for r in self.records(skill)) or "none"
        raise UnknownRecord(
            f"{self.path}: no record {name!r} for skill {skill!r} (taught: {known})"
        )

    def find(self, name: str) -> TaughtRecord:
        """The record called ``name`` (``skill/name`` also works) whatever its skill."""
        if "/" in name:
            skill, _, rest = name.partition("/")
            return self.get(skill, rest)
        matches = [r for r in self._read() if r.name == name]
        if not matches:
            raise UnknownRecord(f"{self.path}: no record named {name!r}")
        if len(matches) > 1:
            keys = ", ".join(r.key for r in matches)
            raise UnknownRecord(f"{self.path}: {name!r} is ambiguous ({keys}); say skill/name")
        return matches[0]

    def put(self, record: TaughtRecord) -> TaughtRecord:
        """Store ``record`` (replacing one of the same skill and name, whose revision + 1 it
        gets); returns the record as stored."""
        records = self._read()
        revision = 1
        for r in records:
            if r.key == record.key:
                revision = r.revision + 1
        stored = TaughtRecord(
            record.skill,
            record.name,
            dict(record.params),
            record.frame,
            revision,
            record.taught_at,
            record.notes,
        )
        self._write([r for r in records if r.key != record.key] + [stored])
        return stored

    def remove(self, skill: str, name: str) -> None:
        records = self._read()
        kept = [r for r in records if not (r.skill == skill and r.name == name)]
        if len(kept) == len(records):
            raise UnknownRecord(f"{self.path}: no record {name!r} for skill {skill!r}")
        self._write(kept)

    def save(self) -> None:
        """Rewrite the file in the current schema (after reading an older one)."""
        self._write(self._read())
