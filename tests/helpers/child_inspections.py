"""Inspections for the process lane's tests: importable by a spawned worker process (the
tests' helpers are on the path it inherits), and picklable."""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from vision_server.catalog import InspectionInput, InspectionOutcome


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
            "mean": float(np.mean(image.color)),
            "depth": [[list(d.shape), int(d.sum())] for d in image.depth],
        }
        drawn = (255 - image.color) if overlay else None
        return InspectionOutcome(True, data, drawn)
