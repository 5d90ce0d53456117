"""The configuration file's version history: every text the console wrote, with who, when and
why, bounded on disk.

The versions of ``cell.yaml`` live in the folder ``cell.yaml.history/`` beside it, one file
per version, ``v000001.version``, ``v000002.version``, ...: a first line of JSON (the version's
metadata, :class:`Version`) and, after it, the file's whole text byte for byte. One file per
version, written to a temporary file, synced and renamed into place (a hard link that refuses
to overwrite), so a crash leaves either the whole version or none; listing reads only the
first line of each file it shows.

Bounded (:class:`Bounds`): after each version is written the oldest are deleted while more
than ``max_versions`` are kept or their files hold more than ``max_bytes``; the newest is
always kept. Only files of this folder whose names are versions' are ever deleted.

No holes: before a version is written, the text the file has now is compared with the newest
version's; when they differ (an edit made outside the console) that text is recorded first
(kind ``edited_outside``, who ``unknown``), and the first version of a file with no history
is its text as found (kind ``original``).
"""

from __future__ import annotations

import contextlib
import difflib
import hashlib
import json
import os
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .document import ConfigError, parse_document
from .files import replace_file, write_new

SAVE = "save"
"""A save of tuned values from the console."""
REVERT = "revert"
"""A revert to an earlier version's text."""
CREATED_INSPECTION = "created_inspection"
"""A new inspection written by the console."""
EDITED_OUTSIDE = "edited_outside"
"""The file as found before a console write: edited by hand (or another program) since."""
ORIGINAL = "original"
"""The file as found when its history began."""
KINDS = (SAVE, REVERT, CREATED_INSPECTION, EDITED_OUTSIDE, ORIGINAL)

UNKNOWN = "unknown"
"""Who made a version the console did not write."""
MAX_WHY = 500
"""The longest reason (characters) a version keeps."""
MAX_WHO = 100
"""The longest name (characters) a version keeps."""
MAX_HEADER = 64 * 1024
"""The longest metadata line read back (bytes): a longer one is not a version of ours."""
MAX_DIFF_LINES = 20_000
"""A diff is cut after this many lines (with a last line saying so)."""
MAX_DIFF_BYTES = 1 << 20
"""The largest text compared for a diff, bytes (as the console writes at most)."""

STALE_TMP_S = 3600.0
"""A temporary file of the history's folder older than this (seconds) is a write a crash cut
short: the next write deletes it."""

SUFFIX = ".history"
_NAME = re.compile(r"v(\d{6,12})\.version\Z")


class HistoryError(OSError):
    """The history cannot be read or written (its folder is not a folder of ours, a version
    file that is not one): a file-system error, as the configuration file's own."""


class UnknownVersion(HistoryError):
    """No such version is kept (never made, or dropped by the bounds)."""


@dataclass(frozen=True)
class Bounds:
    """How much history is kept: at most ``max_versions`` versions and ``max_bytes`` bytes of
    version files (the newest is kept whatever its size). ``console: history_max_versions``
    and ``history_max_mb`` in the configuration."""

    max_versions: int = 200
    max_bytes: int = 50 * 1024 * 1024


@dataclass(frozen=True)
class Version:
    """One version's metadata. ``time``: Unix seconds when it was written; ``size``: bytes
    of its text; ``config_hash``: the hash the server reports for that text;
    ``inspections``: names of the inspections whose parsed configuration differs from the
    previous version's (added, removed or changed; empty when either text does not parse);
    ``reverted_to``: for a revert, the version whose text it restored."""

    number: int
    time: float
    who: str
    why: str
    kind: str
    config_hash: str
    size: int
    inspections: tuple[str, ...] = ()
    reverted_to: int | None = None
    parsed: bool = True
    """Whether the text parsed as YAML when it was recorded (a broken hand edit does not)."""

    def json(self) -> dict[str, Any]:
        return {
            "version": self.number,
            "time": self.time,
            "who": self.who,
            "why": self.why,
            "kind": self.kind,
            "config_hash": self.config_hash,
            "size": self.size,
            "inspections": list(self.inspections),
            "reverted_to": self.reverted_to,
            "parsed": self.parsed,
        }

    @classmethod
    def from_json(cls, data: Any) -> Version:
        if not isinstance(data, dict):
            raise ValueError("not a mapping")
        number, moment = data["version"], data["time"]
        if not isinstance(number, int) or not isinstance(moment, int | float):
            raise ValueError("bad version or time")
        names = data.get("inspections") or []
        reverted = data.get("reverted_to")
        return cls(
            number=number,
            time=float(moment),
            who=str(data.get("who", UNKNOWN)),
            why=str(data.get("why", "")),
            kind=str(data.get("kind", SAVE)),
            config_hash=str(data.get("config_hash", "")),
            size=int(data.get("size", 0)),
            inspections=tuple(str(n) for n in names) if isinstance(names, list) else (),
            reverted_to=reverted if isinstance(reverted, int) else None,
            parsed=bool(data.get("parsed", True)),
        )


def config_hash(data: bytes) -> str:
    """The configuration hash of a file's bytes, as the loader computes it for its text
    (:class:`~vision_server.config.CellConfig`'s ``config_hash``)."""
    return hashlib.sha256(data).hexdigest()[:16]


def changed_between(old: bytes | None, new: bytes) -> tuple[tuple[str, ...], bool]:
    """Names of the inspections whose parsed configuration differs between the texts ``old``
    and ``new`` (added, removed or changed, in ``new``'s order then the removed ones), and
    whether ``new`` parses at all. ``old`` None: every inspection of ``new``."""
    after = _inspections(new)
    if after is None:
        return (), False
    before = {} if old is None else _inspections(old)
    if before is None:
        return (), True
    names = [n for n, item in after.items() if before.get(n) != item]
    names += [n for n in before if n not in after]
    return tuple(names), True


def _inspections(data: bytes) -> dict[str, Any] | None:
    """The inspections of a configuration text by name, as parsed (None: it does not parse)."""
    try:
        root = parse_document(data.decode("utf-8"), source="history").data
    except (ConfigError, UnicodeError, ValueError, RecursionError):
        return None
    items = root.get("inspections") if isinstance(root, dict) else None
    out: dict[str, Any] = {}
    for index, item in enumerate(items if isinstance(items, list) else []):
        name = item.get("name") if isinstance(item, dict) else None
        out[str(name) if name is not None else f"#{index + 1}"] = item
    return out


class History:
    """The versions of the configuration file ``config`` (in ``config.history/`` beside it),
    kept within ``bounds``. Reading never creates or changes anything."""

    def __init__(self, config: Path, bounds: Bounds | None = None) -> None:
        self.config = config
        self.folder = config.with_name(config.name + SUFFIX)
        self.bounds = bounds or Bounds()

    # ------------------------------------------------------------------ reading

    def numbers(self) -> list[int]:
        """The kept versions' numbers, oldest first."""
        return [n for n, _ in self._entries()]

    def versions(self, *, before: int | None = None, limit: int = 50) -> list[Version]:
        """Up to ``limit`` versions older than ``before`` (all when None), newest first."""
        entries = [e for e in self._entries() if before is None or e[0] < before]
        out = []
        for _, path in reversed(entries[-limit:] if limit > 0 else []):
            with contextlib.suppress(HistoryError):
                out.append(self._read(path)[0])
        return out

    def newest(self) -> Version | None:
        entries = self._entries()
        return None if not entries else self._read(entries[-1][1])[0]

    def get(self, number: int) -> Version:
        return self._read(self._path(number))[0]

    def text(self, number: int) -> bytes:
        """Version ``number``'s text, byte for byte."""
        return self._read(self._path(number), body=True)[1]

    def previous(self, number: int) -> int | None:
        """The number of the kept version before ``number`` (None: it is the oldest kept)."""
        older = [n for n in self.numbers() if n < number]
        return older[-1] if older else None

    def diff(self, number: int, shown: Callable[[str], str] = str) -> str:
        """A unified diff from the previous kept version's text to version ``number``'s
        (from an empty text for the oldest kept), at most :data:`MAX_DIFF_LINES` lines; each
        text as ``shown`` shows it (e.g. its secrets hidden: it must keep the lines)."""
        new = self.text(number)
        before = self.previous(number)
        old = b"" if before is None else self.text(before)
        if max(len(old), len(new)) > MAX_DIFF_BYTES:
            # Matching is quadratic in the worst case: a huge hand-edited version (the console
            # writes none over 1 MiB) is not compared, whoever asks.
            return (
                f"... (not compared: version {number} or the one before has more than "
                f"{MAX_DIFF_BYTES} bytes)\n"
            )
        lines = difflib.unified_diff(
            shown(old.decode("utf-8", "replace")).splitlines(keepends=True),
            shown(new.decode("utf-8", "replace")).splitlines(keepends=True),
            fromfile="(nothing kept)" if before is None else f"version {before}",
            tofile=f"version {number}",
        )
        out: list[str] = []
        for index, line in enumerate(lines):
            if index == MAX_DIFF_LINES:
                out.append(f"... (the diff is cut after {MAX_DIFF_LINES} lines)\n")
                break
            out.append(line if line.endswith("\n") else line + "\n\\ No newline at end of file\n")
        return "".join(out)

    # ------------------------------------------------------------------ writing

    def catch_up(self, current: bytes) -> Version | None:
        """Record ``current`` (the file's bytes now) when the history does not end with it:
        as the ``original`` when there is no history yet, else as ``edited_outside``. Returns
        the version written, or None when the newest version already holds that text."""
        entries = self._entries()
        if entries:
            newest_path = entries[-1][1]
            try:
                if self._read(newest_path, body=True)[1] == current:
                    return None
            except HistoryError:
                pass  # unreadable newest version: record the file anew
            kind = EDITED_OUTSIDE
        else:
            kind = ORIGINAL
        return self._write(current, who=UNKNOWN, why="", kind=kind, reverted_to=None)

    def record(
        self,
        data: bytes,
        *,
        who: str,
        why: str,
        kind: str = SAVE,
        reverted_to: int | None = None,
    ) -> Version:
        """Write ``data`` as the next version (not pruned yet: see :meth:`prune`)."""
        return self._write(data, who=who, why=why, kind=kind, reverted_to=reverted_to)

    def drop(self, number: int) -> None:
        """Delete version ``number`` (a write it recorded was undone)."""
        with contextlib.suppress(FileNotFoundError):
            self._path(number).unlink()

    def prune(self) -> list[int]:
        """Delete the oldest versions beyond the bounds (never the newest); returns their
        numbers."""
        entries = []
        for number, path in self._entries():
            try:
                entries.append((number, path, path.stat().st_size))
            except OSError:
                continue
        self._sweep()
        dropped: list[int] = []
        total = sum(size for *_, size in entries)
        while len(entries) > 1 and (
            len(entries) > self.bounds.max_versions or total > self.bounds.max_bytes
        ):
            number, path, size = entries.pop(0)
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            total -= size
            dropped.append(number)
        return dropped

    def _sweep(self) -> None:
        """Delete the temporary files of writes that a crash cut short (``.*.tmp`` of this
        folder, older than :data:`STALE_TMP_S`): never a version, never another file."""
        now = time.time()
        with contextlib.suppress(OSError), os.scandir(self.folder) as entries:
            for entry in entries:
                if not (entry.name.startswith(".") and entry.name.endswith(".tmp")):
                    continue
                with contextlib.suppress(OSError):
                    stat = entry.stat(follow_symlinks=False)
                    if entry.is_file(follow_symlinks=False) and now - stat.st_mtime > STALE_TMP_S:
                        os.unlink(entry.path)

    # ------------------------------------------------------------------ files

    def _path(self, number: int) -> Path:
        if isinstance(number, bool) or not isinstance(number, int) or number < 1:
            raise UnknownVersion(f"no version {number!r}: versions are numbered from 1")
        return self.folder / f"v{number:06d}.version"

    def _entries(self) -> list[tuple[int, Path]]:
        """(number, path) of every version file, oldest first (regular files only)."""
        if self.folder.is_symlink():
            raise HistoryError(f"{self.folder.name} is a symbolic link, not the history's folder")
        found: list[tuple[int, Path]] = []
        try:
            scan = os.scandir(self.folder)
        except FileNotFoundError:
            return []
        except OSError as exc:
            raise HistoryError(f"cannot read {self.folder.name}: {exc}") from None
        with scan as entries:
            for entry in entries:
                match = _NAME.match(entry.name)
                if match and entry.is_file(follow_symlinks=False):
                    found.append((int(match.group(1)), Path(entry.path)))
        return sorted(found)

    def _read(self, path: Path, *, body: bool = False) -> tuple[Version, bytes]:
        try:
            with path.open("rb") as file:
                header = file.readline(MAX_HEADER)
                data = file.read() if body else b""
        except FileNotFoundError:
            number = _NAME.match(path.name)
            raise UnknownVersion(
                f"no version {int(number.group(1)) if number else path.name} is kept"
            ) from None
        except OSError as exc:
            raise HistoryError(f"cannot read {path.name}: {exc}") from None
        try:
            version = Version.from_json(json.loads(header))
        except (ValueError, KeyError, TypeError):
            raise HistoryError(f"{path.name} is not a version file") from None
        named = _NAME.match(path.name)
        if named is None or int(named.group(1)) != version.number:
            raise HistoryError(f"{path.name} holds version {version.number}: not its own")
        return version, data

    def _write(
        self, data: bytes, *, who: str, why: str, kind: str, reverted_to: int | None
    ) -> Version:
        if self.folder.is_symlink():
            raise HistoryError(f"{self.folder.name} is a symbolic link, not the history's folder")
        # The configuration may hold tokens: the folder is the owner's alone.
        self.folder.mkdir(mode=0o700, exist_ok=True)
        numbers = self.numbers()
        previous = None
        if numbers:
            with contextlib.suppress(HistoryError):
                previous = self.text(numbers[-1])
        names, parsed = changed_between(previous, data)
        number = (numbers[-1] if numbers else 0) + 1
        while True:
            version = Version(
                number=number,
                time=time.time(),
                who=who[:MAX_WHO],
                why=why[:MAX_WHY],
                kind=kind,
                config_hash=config_hash(data),
                size=len(data),
                inspections=names,
                reverted_to=reverted_to,
                parsed=parsed,
            )
            header = json.dumps(version.json(), ensure_ascii=True).encode("ascii") + b"\n"
            if self._place(self._path(number), header + data):
                return version
            number += 1  # written meanwhile by another process: the next number

    def _place(self, path: Path, content: bytes) -> bool:
        """Write ``content`` as ``path`` atomically and durably, never over an existing file;
        False when ``path`` exists. The mode is the configuration file's."""
        return write_new(path, content, mode_of=self.config)


_BOUNDS: dict[Path, Bounds] = {}


def set_bounds(config: Path, bounds: Bounds) -> None:
    """The bounds of ``config``'s history for every writer in this process (the console sets
    its configured ones once; whichever module writes the file then keeps them)."""
    _BOUNDS[config.resolve()] = bounds


def history_of(config: Path) -> History:
    """``config``'s history with the bounds set for it (:func:`set_bounds`; else defaults)."""
    return History(config, _BOUNDS.get(config.resolve()))


def write_with_history(
    path: Path,
    data: bytes,
    *,
    old: bytes | None = None,
    who: str,
    why: str,
    kind: str = SAVE,
    reverted_to: int | None = None,
) -> Version:
    """Replace the configuration file ``path`` with ``data`` and record it in the file's
    history (the one way the console and ``vision-server train`` write it). First the history
    catches up with the file as it is (an edit made outside becomes a version of its own, the
    file's first text the history's first version), then the new version is written, then the
    file is replaced; each write is atomic, and when replacing the file fails the new version
    is dropped again. Afterwards the oldest versions beyond the history's bounds are deleted.
    ``old``: the file's bytes as read (read now when None). Raises OSError (nothing changed
    but perhaps the catch-up)."""
    if old is None:
        old = path.read_bytes()
    versions = history_of(path)
    versions.catch_up(old)
    version = versions.record(data, who=who, why=why, kind=kind, reverted_to=reverted_to)
    try:
        replace_file(path, data)
    except BaseException:
        versions.drop(version.number)
        raise
    versions.prune()
    return version


__all__ = [
    "CREATED_INSPECTION",
    "EDITED_OUTSIDE",
    "KINDS",
    "MAX_WHY",
    "ORIGINAL",
    "REVERT",
    "SAVE",
    "UNKNOWN",
    "Bounds",
    "History",
    "HistoryError",
    "UnknownVersion",
    "Version",
    "changed_between",
    "config_hash",
    "history_of",
    "set_bounds",
    "write_with_history",
]
