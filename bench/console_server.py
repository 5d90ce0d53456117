"""The console bench's server: the bench catalog (bench/cell.py) plus a live camera of known
frame rate, served with the web console on, each front-end on its own port of 127.0.0.1.

The live camera is the ``opencv`` source playing a video file in real time (a file plays at
its ``fps``, the newest frame "on air", as a camera delivers them: see
vision_server/cameras/opencv.py). :func:`write_config` writes the file (rendered frames of the
simulated QC camera) and the configuration; ``python -m bench.console_server --config PATH``
serves it, prints one JSON line (``port``, ``console_url``, ...) when it listens, and stops
when its standard input closes (run it with :class:`bench.servers.ServerProcess`).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from .cell import config_dict

LIVE_CAMERA = "live"
CAMERA_FPS = 30.0
"""The live camera's own frame rate (frames per second), a usual industrial camera's."""
VIDEO_FRAMES = 60
MAX_VIEW_FPS = 10.0
"""The console's cap on live reads (the example cell's ``console.max_view_fps``)."""


def write_video(path: Path, image: Any, *, frames: int = VIDEO_FRAMES) -> Path:
    """A looping MJPG video of ``image`` (gray or BGR) with its frame number drawn, at
    :data:`CAMERA_FPS`: every frame differs, as a live camera's do."""
    color = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    height, width = color.shape[:2]
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter.fourcc(*"MJPG"), CAMERA_FPS, (width, height)
    )
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write an MJPG video to {path}")
    try:
        for index in range(frames):
            frame = np.ascontiguousarray(color.copy())
            cv2.putText(frame, f"{index:03d}", (20, 60), cv2.FONT_HERSHEY_SIMPLEX, 2.0, 255, 3)
            writer.write(frame)
    finally:
        writer.release()
    return path


def write_config(workdir: Path, image: Any) -> Path:
    """The bench configuration (request cameras, the example's inspections) plus the live
    camera playing :func:`write_video` of ``image``."""
    video = write_video(workdir / "live.avi", image)
    doc = config_dict()
    doc["server"] = {"name": "cellvision-console-bench"}
    doc["cameras"][LIVE_CAMERA] = {
        "source": "opencv",
        "device": str(video),
        "fps": CAMERA_FPS,
        "loop_file": True,
    }
    path = workdir / "bench-console.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


async def _serve(config: Path) -> None:
    from vision_server import ServerSettings, VisionServer
    from vision_server.config import ConsoleSettings

    from .cell import load_catalog

    bench = load_catalog(config)
    if bench.problem:
        raise RuntimeError(bench.problem)
    console = ConsoleSettings(enabled=True, port=0, max_view_fps=MAX_VIEW_FPS)
    server = VisionServer(bench.catalog, ServerSettings(port=0), console=console)
    await server.start()
    assert server.http is not None
    loop = asyncio.get_running_loop()
    done = asyncio.Event()

    def wait() -> None:
        sys.stdin.buffer.read()
        loop.call_soon_threadsafe(done.set)

    threading.Thread(target=wait, daemon=True).start()
    info: dict[str, Any] = {
        "port": server.port,
        "console_url": server.http.url,
        "inspections": sorted(bench.catalog.inspections),
        "workers": server.settings.workers,
        "max_view_fps": MAX_VIEW_FPS,
        "camera_fps": CAMERA_FPS,
    }
    sys.stdout.write(json.dumps(info) + "\n")
    sys.stdout.flush()
    await done.wait()
    await server.stop()


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.console_server")
    parser.add_argument("--config", type=Path, required=True)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    asyncio.run(_serve(args.config))


if __name__ == "__main__":
    main()
