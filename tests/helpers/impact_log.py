"""A result log with stored images for the impact preview's tests, made by a real server run.

:func:`impact_server` runs the example cell (tests/helpers/console_server.py) with
``store_images: all``; :func:`fill_log` sends designed QC images to ``magnet_check`` through the
cellvision protocol (a robot's INSPECT with its image), so that every row, its stored image and
its verdict are the server's own. Half of the rows are made under a first version of the file,
the rest after a reload with an edited comment (another ``config_hash``), and one console try is
among them (which a replay leaves out).

The images are designed so that ``magnet_check``'s verdict (``dark_fraction`` over the ROI
[486, 236, 50, 60] against ``min``) is known without running it: a background of grey 200
(darker than no threshold used here) and, over the top ``fraction`` of the ROI's rows, grey
``gray``. :func:`expected_pass` computes the verdict from the design, independently of the
server.

Importable as ``impact_log`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from console_server import TOKEN, Browserless, RunningConsole, example_config, running_cell

from robot_client.client import SyncVisionClient

ROI = (486, 236, 50, 60)
"""magnet_check's ROI in examples/cell.yaml: u, v, width, height (pixels)."""
SIZE = (1024, 768)
"""The QC camera's image size (width, height), pixels."""
BASE_THRESHOLD = 90
BASE_MIN = 0.25
BACKGROUND = 200


@dataclass(frozen=True)
class Design:
    """One designed image: the ROI's top ``rows`` rows (of 60) are grey ``gray``."""

    gray: int
    rows: int

    @property
    def fraction(self) -> float:
        return self.rows / ROI[3]


DESIGNS = (
    Design(40, 30),  # 0.5 very dark
    Design(40, 18),  # 0.3 very dark
    Design(100, 30),  # 0.5 mid
    Design(100, 18),  # 0.3 mid
    Design(150, 48),  # 0.8 light
    Design(70, 24),  # 0.4 dark
    Design(110, 54),  # 0.9 mid
    Design(60, 6),  # 0.1 dark
)
"""Eight designs; :func:`fill_log` sends each twice (16 rows, 8 per configuration)."""


def expected_pass(design: Design, threshold: float, minimum: float) -> bool:
    """magnet_check's verdict on ``design`` with ``threshold`` and ``min``, from the design."""
    dark = design.fraction if design.gray < threshold else 0.0
    return dark >= minimum


def designed_image(design: Design) -> np.ndarray:
    """The BGR image of ``design``."""
    image = np.full((SIZE[1], SIZE[0], 3), BACKGROUND, np.uint8)
    u, v, w, _ = ROI
    image[v : v + design.rows, u : u + w] = design.gray
    return image


def cell_config(folder: Path) -> Path:
    """The example cell as ``folder/cell.yaml`` with ``store_images: all``."""
    path = example_config(folder)
    text = path.read_text(encoding="utf-8")
    assert "store_images: failures" in text
    path.write_text(text.replace("store_images: failures", "store_images: all"), encoding="utf-8")
    return path


@contextlib.contextmanager
def impact_server(folder: Path) -> Iterator[RunningConsole]:
    with running_cell(cell_config(folder)) as running:
        yield running


@dataclass(frozen=True)
class Row:
    """A row :func:`fill_log` made: its id, design and the config hash it was made under."""

    result_id: int
    design: Design
    config_hash: str


def _inspect(server: RunningConsole, design: Design) -> None:
    with SyncVisionClient("127.0.0.1", server.app.port, auth_token=TOKEN) as client:
        client.inspect("magnet_check", designed_image(design))


def fill_log(server: RunningConsole) -> list[Row]:
    """Send every design twice (the second round after a reload under an edited file) and one
    console try; the production rows made, oldest first."""
    service = server.app.service
    log = service.results
    assert log is not None
    rows: list[Row] = []
    for round_ in range(2):
        if round_ == 1:
            text = server.config.read_text(encoding="utf-8")
            server.config.write_text(text + "\n# edited: another config hash\n", encoding="utf-8")
            asyncio.run_coroutine_threadsafe(service.reload(), server.loop).result(30.0)
        for design in DESIGNS:
            _inspect(server, design)
            newest = log.query(inspection="magnet_check", limit=1)[0]
            assert not newest.is_try
            assert newest.image_path is not None
            rows.append(Row(newest.id, design, newest.config_hash))
        if round_ == 0:
            # A console try among the rows: never replayed (tries are not production).
            client = Browserless(server.url)
            assert client.login().status == 200
            ok, png = cv2.imencode(".png", designed_image(DESIGNS[0]))
            assert ok
            reply = client.try_("magnet_check", {"source": "upload"}, png.tobytes())
            assert reply.status == 200, reply.body
    hashes = {row.config_hash for row in rows}
    assert len(hashes) == 2, hashes
    return rows


def changed_config(server: RunningConsole, folder: Path, threshold: float, minimum: float) -> Path:
    """A copy of the server's file with magnet_check's threshold and min changed."""
    text = server.config.read_text(encoding="utf-8")
    old = f"    threshold: {BASE_THRESHOLD}\n    min: {BASE_MIN}\n"
    assert old in text
    path = folder / "changed.yaml"
    path.write_text(
        text.replace(old, f"    threshold: {threshold}\n    min: {minimum}\n"), encoding="utf-8"
    )
    return path
