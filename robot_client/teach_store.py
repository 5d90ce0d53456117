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

Files are read with ``yaml.safe_load`` only and written atomically (a temporary file in the same
directory, then ``os.replace``), so a reader sees the old or the new file, never half of one.
Errors name the file, the record and the key.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import yaml

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
RECORD_KEYS = {"skill", "name", "revision", "frame", "taught_at", "notes", "params"}


class TeachStoreError(ValueError):
    """A teach store file that cannot be read or written; the message names file, record, key."""


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


# --- records ------------------------------------------------------------------------------


def _record_from_dict(item: Any, index: int) -> TaughtRecord:
    where = f"records[{index}]"
    if not isinstance(item, dict):
        raise TeachStoreError(f"{where}: expected a mapping, got {type(item).__name__}")
    label = f"{where} ({item.get('skill')}/{item.get('name')})"
    unknown = sorted(set(item) - RECORD_KEYS)
    if unknown:
        raise TeachStoreError(f"{label}: unknown key(s) {', '.join(map(repr, unknown))}")

    def text(key: str, default: str | None = None) -> str:
        value = item.get(key, default)
        if not isinstance(value, str) or (default is None and not value):
            raise TeachStoreError(f"{label}: key {key!r}: expected a non-empty string")
        return value

    revision = item.get("revision", 1)
    if isinstance(revision, bool) or not isinstance(revision, int) or revision < 1:
        raise TeachStoreError(f"{label}: key 'revision': expected a positive integer")
    params = item.get("params") or {}
    if not isinstance(params, dict) or not all(isinstance(k, str) for k in params):
        raise TeachStoreError(f"{label}: key 'params': expected a mapping of parameter names")
    return TaughtRecord(
        skill=text("skill"),
        name=text("name"),
        params=params,
        frame=text("frame", "base") or "base",
        revision=revision,
        taught_at=str(item.get("taught_at") or ""),
        notes=text("notes", ""),
    )


class TeachStore:
    """Taught records in the YAML file ``path`` (created on the first :meth:`put`).

    Every read re-reads the file, so several programs (the CLI, a task runner) can share it.
    ``upgraded_from``: the schema version the last read file had, if older than the current.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.upgraded_from: int | None = None

    def _error(self, message: str) -> TeachStoreError:
        return TeachStoreError(f"{self.path}: {message}")

    def _read(self) -> list[TaughtRecord]:
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return []
        except OSError as exc:
            raise self._error(f"cannot read: {exc.strerror or exc}") from exc
        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            line = f" line {mark.line + 1}" if mark is not None else ""
            raise self._error(f"not valid YAML{line}: {getattr(exc, 'problem', exc)}") from None
        if doc is None:
            return []
        if not isinstance(doc, dict):
            raise self._error("expected a mapping at the top level")
        try:
            doc, version = upgrade(doc)
            self.upgraded_from = version if version < SCHEMA_VERSION else None
            if doc.get("format") != FORMAT:
                raise TeachStoreError(
                    f"key 'format': expected {FORMAT!r}, got {doc.get('format')!r}"
                )
            unknown = sorted(set(doc) - {"format", "schema_version", "records"})
            if unknown:
                raise TeachStoreError(f"unknown top-level key(s) {', '.join(map(repr, unknown))}")
            items = doc.get("records") or []
            if not isinstance(items, list):
                raise TeachStoreError("key 'records': expected a list")
            records = [_record_from_dict(item, i) for i, item in enumerate(items)]
        except TeachStoreError as exc:
            raise self._error(str(exc)) from None
        seen: set[str] = set()
        for r in records:
            if r.key in seen:
                raise self._error(f"record {r.key} appears twice")
            seen.add(r.key)
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
