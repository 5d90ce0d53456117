"""Inspections for the process lane's tests: importable by a spawned worker process (the
tests' helpers are on the path it inherits), and picklable."""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from vision_server import InspectionInput, InspectionOutcome


@dataclass(frozen=True)
class WhereAmI:
    """Reports the process it ran in, the niceness of the thread that ran it, and what it saw:
    the mean of the colour image, the depth frames' shapes and sums; its overlay is the image
    inverted."""

    name: str = "where"
    camera: str = "tool"
    type: str = "test_where"
    uses_depth: bool = True
    frames: int = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        data: dict[str, Any] = {
            "pid": os.getpid(),
            "nice": os.getpriority(os.PRIO_PROCESS, threading.get_native_id()),
            "policy": os.sched_getscheduler(0),
            "opencv_threads": cv2.getNumThreads(),
            "mean": float(np.mean(image.color)),
            "depth": [[list(d.shape), int(d.sum())] for d in image.depth],
        }
        drawn = (255 - image.color) if overlay else None
        return InspectionOutcome(True, data, drawn)


_pickled_times = [0]


@dataclass(frozen=True)
class Misbehaving:
    """``how``: ``"die"`` ends its process in the middle of the run (as a crash in native code
    would), ``"refuse"`` raises the inspection error a real inspection raises on a bad image,
    ``"oserror"`` raises an OSError of its own (which is not a dead worker)."""

    how: str
    name: str = "misbehaving"
    camera: str = "tool"
    type: str = "test_misbehaving"
    uses_depth: bool = False
    frames: int = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        if self.how == "die":
            os._exit(3)
        if self.how == "refuse":
            from protocol.errors import InspectionFailed

            raise InspectionFailed("the image shows no part")
        if self.how == "oserror":
            raise FileNotFoundError("template.png")
        return InspectionOutcome(True, {"pid": os.getpid()}, None)


@dataclass(frozen=True)
class CountsItsPickles:
    """Counts in the process that pickles it (the server) how often it was pickled."""

    name: str = "counted"
    camera: str = "tool"
    type: str = "test_counted"
    uses_depth: bool = False
    frames: int = 1

    def __reduce__(self) -> tuple[Any, ...]:
        _pickled_times[0] += 1
        return (CountsItsPickles, (self.name,))

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        return InspectionOutcome(True, {"pid": os.getpid()}, None)


def pickled_times() -> int:
    return _pickled_times[0]


def _refuse_outside(parent: int) -> CountsItsPickles:
    if os.getpid() != parent:
        raise ValueError("this inspection cannot be unpickled in a worker process")
    return CountsItsPickles()


@dataclass(frozen=True)
class UnpicklableInWorkers:
    """Pickles in the server, but its unpickling fails in any other process."""

    name: str = "unpicklable"
    camera: str = "tool"
    type: str = "test_unpicklable"
    uses_depth: bool = False
    frames: int = 1

    def __reduce__(self) -> tuple[Any, ...]:
        return (_refuse_outside, (os.getpid(),))

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        return InspectionOutcome(True, {}, None)
