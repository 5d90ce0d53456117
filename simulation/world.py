"""The mutable world state and the world-state file that shares it between processes.

``World`` holds what changes while the cell runs: the pose of every part (or the tool-relative
pose of the part the gripper holds), the robot's mount ``world_from_base`` (a mobile robot docks
with some error), its tool pose, its user frame, and the simulated time.

Sharing across processes: the process that moves things (the robot client's ``SimCell``) writes
the whole state as JSON to one file after every change, atomically (write a temporary file in the
same directory, then ``os.replace``), with a ``version`` counter that only increases. Any other
process (the vision server's ``sim`` camera) calls :meth:`WorldStateFile.read_if_changed` before
rendering: it stats the file and parses it only when its (mtime, size, inode) changed, and adopts
it only when it comes from another writer (each writer has a random id, so a restarted writer is
followed too) or has a newer version. Readers never see a half-written file. One process should
write; if two do, the last write wins.
"""

from __future__ import annotations

import json
import os
import tempfile
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["FORMAT", "PartState", "World", "WorldStateFile"]

FloatArray = NDArray[np.float64]
FORMAT = "cellvision-world/1"


def _mat(value: Any, what: str) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be a finite 4x4 matrix")
    return arr


@dataclass
class PartState:
    """Where a part is: ``world_from_part`` when free; ``tool_from_part`` while held.

    ``location`` names what it rests on (a surface, bin or box name; '' while held).
    """

    world_from_part: FloatArray
    held: bool = False
    tool_from_part: FloatArray | None = None
    location: str = ""


@dataclass
class World:
    """Mutable state of the simulated cell. Poses in metres; see the module docstring."""

    parts: dict[str, PartState]
    world_from_base: FloatArray
    base_from_tool: FloatArray
    base_from_user: FloatArray = field(default_factory=lambda: np.eye(4))
    time_s: float = 0.0
    version: int = 0

    def world_from_tool(self) -> FloatArray:
        result: FloatArray = self.world_from_base @ self.base_from_tool
        return result

    def part_pose(self, name: str) -> FloatArray:
        """``world_from_part`` of a part, following the tool while it is held."""
        state = self.parts[name]
        if state.held and state.tool_from_part is not None:
            result: FloatArray = self.world_from_tool() @ state.tool_from_part
            return result
        return state.world_from_part

    def held_part(self) -> str | None:
        for name, state in self.parts.items():
            if state.held:
                return name
        return None

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": self.version,
            "time_s": self.time_s,
            "world_from_base": self.world_from_base.tolist(),
            "base_from_tool": self.base_from_tool.tolist(),
            "base_from_user": self.base_from_user.tolist(),
            "parts": {
                name: {
                    "world_from_part": s.world_from_part.tolist(),
                    "held": s.held,
                    "tool_from_part": None
                    if s.tool_from_part is None
                    else s.tool_from_part.tolist(),
                    "location": s.location,
                }
                for name, s in self.parts.items()
            },
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> World:
        if data.get("format") != FORMAT:
            raise ValueError(f"not a world-state document (format {data.get('format')!r})")
        parts = {}
        for name, s in data["parts"].items():
            tfp = s.get("tool_from_part")
            parts[str(name)] = PartState(
                world_from_part=_mat(s["world_from_part"], f"parts.{name}.world_from_part"),
                held=bool(s["held"]),
                tool_from_part=None if tfp is None else _mat(tfp, f"parts.{name}.tool_from_part"),
                location=str(s.get("location", "")),
            )
        return cls(
            parts=parts,
            world_from_base=_mat(data["world_from_base"], "world_from_base"),
            base_from_tool=_mat(data["base_from_tool"], "base_from_tool"),
            base_from_user=_mat(data["base_from_user"], "base_from_user"),
            time_s=float(data["time_s"]),
            version=int(data["version"]),
        )

    def copy(self) -> World:
        return World.from_dict(self.to_dict())


class WorldStateFile:
    """A world-state JSON file: atomic writes, cheap change detection on read."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.writer_id = uuid.uuid4().hex
        self._stamp: tuple[int, int, int] | None = None
        self._last: tuple[str, int] = ("", -1)

    def write(self, world: World) -> None:
        """Write ``world`` atomically (temporary file + ``os.replace``)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        doc = world.to_dict()
        doc["writer"] = self.writer_id
        payload = json.dumps(doc, separators=(",", ":"))
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as handle:
                handle.write(payload)
            os.replace(tmp, self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        self._last = (self.writer_id, world.version)

    def _read_doc(self) -> dict[str, Any]:
        with self.path.open(encoding="utf-8") as handle:
            doc = json.load(handle)
        if not isinstance(doc, dict):
            raise ValueError(f"{self.path}: not a world-state document")
        return doc

    def read(self) -> World:
        """Read the file unconditionally (``FileNotFoundError`` if absent)."""
        return World.from_dict(self._read_doc())

    def read_if_changed(self) -> World | None:
        """The world in the file if it changed since the last call and is newer, else None."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return None
        stamp = (st.st_mtime_ns, st.st_size, st.st_ino)
        if stamp == self._stamp:
            return None
        doc = self._read_doc()
        self._stamp = stamp
        world = World.from_dict(doc)
        writer = str(doc.get("writer", ""))
        last_writer, last_version = self._last
        if writer == last_writer and world.version <= last_version:
            return None
        self._last = (writer, world.version)
        return world
