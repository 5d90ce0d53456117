"""A cell with anomaly inspections and a result log of good parts, for the console's training
tests (tests/vision_server/test_console_train*.py).

:func:`train_config` is the example cell (tests/helpers/console_server.py) with ``store_images:
all`` and two anomaly inspections: ``surface_check`` on the robot's camera ``tool`` (images
arrive in requests; 1024x768) and ``qc_surface`` on the simulated QC camera (frames can be
grabbed), both with a 128x128 ROI and the classical ``variation`` method (trained in a fraction
of a second), and the job ``surface_job`` on ``tool`` with two anomaly steps (``left`` on the
same ROI, ``right`` elsewhere with the default ``patches`` method). :func:`send_parts` sends
designed parts to ``surface_check`` through the cellvision protocol, as a robot does, so that
every row and its stored image are the server's own: before training each ends in
INSPECTION_FAILED ("no trained model"), its image kept.

A good part is a machined part's picture with a little seeded noise; a bad part has a dark
scratch across the ROI.

Importable as ``train_cell`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from console_server import TOKEN, RunningConsole, example_config, running_cell
from console_users import users_yaml

from protocol import CellvisionError
from robot_client.client import SyncVisionClient

ROI = (448, 320, 128, 128)
"""surface_check's ROI: u, v, width, height (pixels)."""
SIZE = (1024, 768)
"""The tool camera's image size (width, height), pixels."""
INSPECTIONS = f"""
  - name: surface_check
    type: anomaly        # trained from the console
    camera: tool
    roi: [{ROI[0]}, {ROI[1]}, {ROI[2]}, {ROI[3]}]
    method: variation

  - name: qc_surface
    type: anomaly
    camera: qc
    roi: [440, 200, 128, 128]
    method: variation

  - name: surface_job
    type: job
    camera: tool
    steps:
      - name: left
        type: anomaly
        roi: [{ROI[0]}, {ROI[1]}, {ROI[2]}, {ROI[3]}]
        method: variation
      - name: right
        type: anomaly
        roi: [280, 160, 128, 128]
"""


def train_config(folder: Path, *, token: str | None = TOKEN) -> Path:
    """The example cell as ``folder/cell.yaml`` with ``store_images: all``, the named users
    of tests/helpers/console_users.py (Carla the integrator, anna the operator) and the two
    anomaly inspections first in its list."""
    path = example_config(folder, token=token, extra_server=f"  users: {users_yaml()}\n")
    text = path.read_text(encoding="utf-8")
    assert "store_images: failures" in text
    assert "\ninspections:\n" in text
    text = text.replace("store_images: failures", "store_images: all")
    text = text.replace("\ninspections:\n", "\ninspections:" + INSPECTIONS + "\n", 1)
    path.write_text(text, encoding="utf-8")
    return path


@contextlib.contextmanager
def train_server(folder: Path, *, token: str | None = TOKEN) -> Iterator[RunningConsole]:
    with running_cell(train_config(folder, token=token)) as running:
        yield running


def _texture() -> np.ndarray:
    """A machined part's picture: a lit gradient, bored holes and a milled pocket, smooth
    enough that screenshots of it stay small."""
    height, width = SIZE[1], SIZE[0]
    rows, cols = np.mgrid[0:height, 0:width]
    grey = 110 + 60 * cols / width + 30 * rows / height
    for cx, cy, r in ((470, 350, 18), (540, 410, 26), (300, 200, 60), (760, 560, 45)):
        grey[(cols - cx) ** 2 + (rows - cy) ** 2 < r * r] = 55
    grey[300:330, 480:560] = 90
    grey = np.clip(grey, 0, 255).astype(np.uint8)
    return np.stack([grey, grey, grey], axis=2)


TEXTURE = _texture()


def part_image(seed: int, *, scratch: bool = False) -> np.ndarray:
    """A part's whole BGR image: the texture, seeded noise of a few grey levels, and with
    ``scratch`` a dark line across the ROI."""
    rng = np.random.default_rng(seed)
    noise = rng.integers(-3, 4, size=TEXTURE.shape, dtype=np.int16)
    image = np.clip(TEXTURE.astype(np.int16) + noise, 0, 255).astype(np.uint8)
    if scratch:
        u, v, w, h = ROI
        for i in range(w - 20):
            image[v + 20 + i // 2 : v + 24 + i // 2, u + 10 + i] = 5
    return image


def inspect(server: RunningConsole, name: str, image: np.ndarray) -> object:
    """One robot INSPECT of ``name`` with ``image``: its Result, or the error it ended in."""
    with SyncVisionClient("127.0.0.1", server.app.port, auth_token=TOKEN) as client:
        try:
            return client.inspect(name, image)
        except CellvisionError as exc:
            return exc


def send_parts(server: RunningConsole, count: int, *, first_seed: int = 0) -> list[int]:
    """Send ``count`` good parts to surface_check; the ids of the rows they made, oldest
    first (each with its stored image)."""
    log = server.app.service.results
    assert log is not None
    ids: list[int] = []
    with SyncVisionClient("127.0.0.1", server.app.port, auth_token=TOKEN) as client:
        for seed in range(first_seed, first_seed + count):
            with contextlib.suppress(CellvisionError):
                client.inspect("surface_check", part_image(seed))
            newest = log.query(inspection="surface_check", limit=1)[0]
            assert newest.image_path is not None
            assert newest.image_path.is_file()
            ids.append(newest.id)
    return ids
