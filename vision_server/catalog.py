"""What a server offers: its cameras and named inspections, as one immutable catalog.

A catalog is swapped whole on a configuration reload, so a request sees either the old or the
new configuration, never a mix.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy.typing as npt

from protocol import UnknownCamera, UnknownInspection

from .cameras import Camera, Intrinsics

Image = npt.NDArray[Any]


@dataclass(frozen=True)
class InspectionInput:
    """The images one inspection run gets.

    ``color``: (H, W) or (H, W, 3) uint8 (BGR); ``depth``: zero or more (H, W) uint16 frames in
    millimetres, registered to ``color``; ``intrinsics``: the camera's, when known.
    """

    color: Image
    depth: tuple[Image, ...] = ()
    intrinsics: Intrinsics | None = None


@dataclass(frozen=True)
class InspectionOutcome:
    """What an inspection found: the verdict, the measured data (JSON-able), an overlay."""

    passed: bool
    data: dict[str, Any] = field(default_factory=dict)
    overlay: Image | None = None


class Inspection(Protocol):
    """A named, configured inspection. ``run`` is CPU-bound and runs in a worker thread.

    ``frames``: how many frames a server camera captures for one run (depth averaging).
    """

    @property
    def name(self) -> str: ...

    @property
    def type(self) -> str: ...

    @property
    def camera(self) -> str: ...

    @property
    def uses_depth(self) -> bool: ...

    @property
    def frames(self) -> int: ...

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome: ...


@dataclass(frozen=True)
class Catalog:
    cameras: Mapping[str, Camera]
    inspections: Mapping[str, Inspection]
    config_hash: str = ""
    notes: tuple[str, ...] = ()
    """What the configuration's reader should know that serving it does not show, e.g. that
    changed ``server:`` settings take effect after a restart (sent in RELOADED)."""

    @classmethod
    def build(
        cls,
        cameras: Sequence[Camera],
        inspections: Sequence[Inspection],
        *,
        config_hash: str | None = None,
    ) -> Catalog:
        cams = {c.name: c for c in cameras}
        insp = {i.name: i for i in inspections}
        for inspection in inspections:
            if inspection.camera not in cams:
                raise ValueError(
                    f"inspection {inspection.name!r} uses camera {inspection.camera!r}, "
                    f"which is not configured"
                )
        if config_hash is None:
            summary = json.dumps(
                {
                    "cameras": [c.descriptor() for c in cameras],
                    "inspections": [[i.name, i.type, i.camera] for i in inspections],
                },
                sort_keys=True,
            )
            config_hash = hashlib.sha256(summary.encode()).hexdigest()[:16]
        return cls(cams, insp, config_hash)

    def inspection(self, name: str, *, request_id: int = 0) -> Inspection:
        try:
            return self.inspections[name]
        except KeyError:
            raise UnknownInspection(
                f"no inspection named {name!r}; configured: {sorted(self.inspections)}",
                request_id=request_id,
            ) from None

    def camera(self, name: str, *, request_id: int = 0) -> Camera:
        try:
            return self.cameras[name]
        except KeyError:
            raise UnknownCamera(
                f"no camera named {name!r}; configured: {sorted(self.cameras)}",
                request_id=request_id,
            ) from None

    def inspection_descriptors(self) -> tuple[dict[str, Any], ...]:
        out = []
        for inspection in self.inspections.values():
            camera = self.cameras[inspection.camera]
            out.append(
                {
                    "name": inspection.name,
                    "type": inspection.type,
                    "camera": inspection.camera,
                    "camera_source": camera.source,
                    "depth": inspection.uses_depth,
                }
            )
        return tuple(out)

    def camera_descriptors(self) -> tuple[dict[str, Any], ...]:
        return tuple(c.descriptor() for c in self.cameras.values())
