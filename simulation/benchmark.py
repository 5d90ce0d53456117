"""Render-time benchmark: ``python -m simulation.benchmark [--frames N] [--scene PATH]``.

Renders the example cell's 1024x768 tool camera looking down at the conveyor (rotor caps in
view) and prints the median wall-clock time per frame in milliseconds.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from geometry import transform_from_xyz_rpy
from simulation.cell import SimCell

DEFAULT_SCENE = (
    Path(__file__).resolve().parent.parent / "examples" / "scenes" / "grundfos_cell.yaml"
)


def measure(scene: Path, frames: int, camera: str = "tool_camera") -> list[float]:
    """Seconds per rendered frame (after one warm-up frame)."""
    cell = SimCell.from_yaml(scene)
    cell.robot.move_linear(transform_from_xyz_rpy([0.3, -0.55, 0.275], [np.pi, 0.0, 0.0]))
    cell.render(camera)
    times = []
    for _ in range(frames):
        start = time.perf_counter()
        cell.render(camera)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--camera", default="tool_camera")
    args = parser.parse_args()
    times = measure(args.scene, args.frames, args.camera)
    ms = [t * 1000 for t in times]
    print(
        f"{args.camera}: median {statistics.median(ms):.2f} ms, "
        f"p90 {np.percentile(ms, 90):.2f} ms over {len(ms)} frames"
    )


if __name__ == "__main__":
    main()
