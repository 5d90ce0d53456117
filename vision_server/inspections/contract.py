"""What every inspection is: the :class:`Inspection` protocol that each type implements, the
images one run gets (:class:`InspectionInput`) and what it found (:class:`InspectionOutcome`).

The service runs inspections through this contract alone; it holds no type's details.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy.typing as npt

from ..cameras import Intrinsics

Image = npt.NDArray[Any]
"""An image array: (H, W) or (H, W, 3) uint8, or a (H, W) uint16 depth frame in millimetres."""


@dataclass(frozen=True)
class InspectionInput:
    """The images one inspection run gets.

    ``color``: (H, W) or (H, W, 3) uint8 (BGR); ``depth``: zero or more (H, W) uint16 frames in
    millimetres, registered to ``color``; ``intrinsics``: the camera's, when known;
    ``deadline``: when (``time.monotonic()`` seconds, one clock for every process of the
    machine) the request stops waiting, or None: an inspection of many parts (a job's steps)
    stops between them once it has passed, so that work nobody waits for does not hold a
    worker.
    """

    color: Image
    depth: tuple[Image, ...] = ()
    intrinsics: Intrinsics | None = None
    deadline: float | None = None


@dataclass(frozen=True)
class InspectionOutcome:
    """What an inspection found: the verdict, the measured data (JSON-able), an overlay."""

    passed: bool
    data: dict[str, Any] = field(default_factory=dict)
    overlay: Image | None = None


class Inspection(Protocol):
    """A named, configured inspection. ``run`` is CPU-bound and must not block (no sleeps, no
    waits on devices or locks): it runs in a worker thread or process, or, when it has proven
    cheap (``inline_ms``), on the server's event loop itself, where a wait would hold up every
    connection until the run is measured as slow.

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
