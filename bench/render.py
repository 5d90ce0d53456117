"""7. Simulation render time per frame, for each camera of the example cell
(``simulation.benchmark.measure``: the robot over the conveyor, one warm-up frame), against a
5x5 Gaussian blur of an image of the same size measured in the same run."""

from __future__ import annotations

from pathlib import Path

from simulation.benchmark import measure
from simulation.scene import load_scene

from .common import SCENE, RunConfig, Section, Stats, Table, fmt, ratio, yardstick_ms
from .env import Env
from .plots import pyplot, save

NAME = "render"
TITLE = "7. Simulation render time per frame"
FRAME_30FPS_MS = 1000.0 / 30.0
TARGET_MS = 15.0  # simulation/README.md, for the 1024x768 tool camera on the 2-core CI machine


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    scene = load_scene(SCENE)
    frames = cfg.n(40, 2)
    table = Table(
        [
            "camera",
            "size",
            "depth",
            "frames",
            "p50 ms",
            "p99 ms",
            "p50 ÷ blur of the same size",
            "p50 ÷ 30 fps frame (33.3 ms)",
        ]
    )
    samples: dict[str, list[float]] = {}
    for spec in scene.cameras:
        intr = spec.intrinsics
        blur = yardstick_ms((intr.height, intr.width), repeat=cfg.n(50, 3))
        times = [t * 1000.0 for t in measure(SCENE, frames, spec.name)]
        samples[spec.name] = times
        s = Stats.of(times)
        table.add(
            spec.name,
            f"{intr.width}x{intr.height}",
            "yes" if spec.depth is not None else "no",
            s.n,
            fmt(s.p50, 2),
            fmt(s.p99, 2),
            ratio(s.p50, blur),
            ratio(s.p50, FRAME_30FPS_MS),
        )
        section.value(f"{spec.name}_p50_ms", s.p50)
        section.value(f"{spec.name}_p99_ms", s.p99)
        section.value(f"{spec.name}_blur_ms", blur)
    section.intro = (
        "Wall-clock time of `SimCell.render(camera)` (geometry, rasterisation with "
        "supersampling, shading, noise; depth with the structured-light model where the camera "
        "has it) for each camera of examples/scenes/grundfos_cell.yaml, with the robot over "
        "the conveyor. The yardstick is a 5x5 Gaussian blur (OpenCV) of an image of the "
        "camera's size."
    )
    section.tables.append(table)
    tool = section.values.get("tool_camera_p50_ms")
    if tool is not None:
        section.notes.append(
            f"simulation/README.md targets <= {TARGET_MS:g} ms per 1024x768 tool-camera frame "
            f"on the 2-core CI machine; measured here: {fmt(tool, 2)} ms (p50)."
        )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(7, 3.5))
        names = list(samples)
        ax.boxplot([samples[n] for n in names], showfliers=True)
        ax.set_xticks(range(1, len(names) + 1), names)
        ax.axhline(FRAME_30FPS_MS, color="grey", linestyle="--", label="30 fps frame period")
        ax.set_ylabel("render time per frame [ms]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        return [save(fig, directory / "render.png")]

    section.plot = plot
    return section
