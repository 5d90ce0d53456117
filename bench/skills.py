"""Harness for the skill benchmarks (sections 4 and 5): the robot client's skills on the
simulated cell against the bench's vision server, with the time split into what a real cell
would spend and what is only the simulation's.

- :class:`TimedVision` wraps the vision client: wall time and the server's ``compute_ms`` of
  every INSPECT.
- :class:`TimedCamera` wraps a simulated camera: counts frames (a real camera delivers them at
  ``FPS``) and measures the render time (the simulation's cost, not the cell's).
- :class:`ReplayCamera` hands out one capture again (several methods on the same frames).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

from robot_client.devices import Capture
from robot_client.devices.sim import SimCamera

FPS = 30.0


@dataclass
class Call:
    inspection: str
    wall_ms: float
    compute_ms: float


@dataclass
class TimedVision:
    """A :class:`robot_client.devices.Vision` that records every INSPECT's timing."""

    client: Any
    calls: list[Call] = field(default_factory=list)

    def inspect(self, inspection: str, image: Any = None, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        result = self.client.inspect(inspection, image, **kwargs)
        wall = (time.perf_counter() - t0) * 1000.0
        compute = float(dict(result.timing or {}).get("compute_ms", float("nan")))
        self.calls.append(Call(inspection, wall, compute))
        return result

    def ping(self, data: str = "") -> float:
        return float(self.client.ping(data))

    def list_inspections(self) -> tuple[dict[str, Any], ...]:
        return tuple(self.client.list_inspections())

    def capture(self, camera: str, **kwargs: Any) -> Any:
        return self.client.capture(camera, **kwargs)


class TimedCamera(SimCamera):
    """A simulated camera that counts the frames it delivers and the time spent rendering."""

    frames = 0
    render_ms = 0.0
    sim_times: list[float]
    """The simulated clock at each capture (where the robot's motion had got to)."""

    def capture(self, *, depth_frames: int = 0) -> Capture:
        if not hasattr(self, "sim_times"):
            self.sim_times = []
        self.sim_times.append(self.cell.clock.now())
        t0 = time.perf_counter()
        cap = super().capture(depth_frames=depth_frames)
        self.render_ms += (time.perf_counter() - t0) * 1000.0
        self.frames += max(1, depth_frames)
        return cap


@dataclass
class ReplayCamera:
    """Hands out ``capture`` (its first ``depth_frames`` depth frames) on every call."""

    source: SimCamera
    stored: Capture

    @property
    def name(self) -> str:
        return self.source.name

    @property
    def intrinsics(self) -> Any:
        return self.source.intrinsics

    @property
    def has_depth(self) -> bool:
        return self.source.has_depth

    @property
    def tool_from_camera(self) -> Any:
        return self.source.tool_from_camera

    def capture(self, *, depth_frames: int = 0) -> Capture:
        return replace(self.stored, depth=self.stored.depth[:depth_frames])
