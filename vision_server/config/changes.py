"""What a reload changes: sentences comparing the configuration served with the new one.

A reload applies the whole file, also edits someone made by hand since the last one; the person
who asked for it (a console save, ``vision-server reload``, SIGHUP in the log) is told what
changed, e.g. ``2 inspections changed: replay_job, label_code``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .cell import CellConfig

__all__ = ["NOTHING_CHANGED", "changed_inspections", "describe_changes"]

NOTHING_CHANGED = "no inspection or camera changed"


def _inspections(config: CellConfig) -> dict[str, Any]:
    """Each inspection as written in the file (after merge keys), else as parsed."""
    written: Mapping[str, Any] | None = getattr(config.tune, "written", None)
    if isinstance(written, Mapping):
        return {name: written[name] for name in written}
    return {spec.name: spec for spec in config.inspections}


def changed_inspections(old: CellConfig, new: CellConfig) -> list[str]:
    """The names of inspections in both whose configuration differs, in the new file's order."""
    before, after = _inspections(old), _inspections(new)
    return [name for name in after if name in before and before[name] != after[name]]


def _sentence(count_of: str, verb: str, names: list[str]) -> str | None:
    if not names:
        return None
    noun = count_of if len(names) == 1 else count_of + "s"
    return f"{len(names)} {noun} {verb}: {', '.join(names)}"


def describe_changes(old: CellConfig, new: CellConfig) -> tuple[str, ...]:
    """What serving ``new`` instead of ``old`` changes, one sentence per kind: inspections and
    cameras changed, added, removed (empty when none of them differs)."""
    before, after = _inspections(old), _inspections(new)
    sentences = [
        _sentence("inspection", "changed", changed_inspections(old, new)),
        _sentence("inspection", "added", [n for n in after if n not in before]),
        _sentence("inspection", "removed", [n for n in before if n not in after]),
        _sentence(
            "camera",
            "changed",
            [n for n in new.cameras if n in old.cameras and old.cameras[n] != new.cameras[n]],
        ),
        _sentence("camera", "added", [n for n in new.cameras if n not in old.cameras]),
        _sentence("camera", "removed", [n for n in old.cameras if n not in new.cameras]),
    ]
    return tuple(s for s in sentences if s is not None)
