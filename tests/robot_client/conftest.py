"""A real vision server on loopback with a copy of examples/cell.yaml, for the skills'
end-to-end tests."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from loopback import server_in_thread

from vision_server.service import CellRuntime

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE_CONFIG = ROOT / "examples" / "cell.yaml"
SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"


def _cell_config(tmp: Path, state_path: Path, extra: str = "") -> Path:
    """A copy of examples/cell.yaml writing into ``tmp`` (results) and reading ``state_path``
    (the qc camera's world), with ``extra`` YAML appended to its inspections."""
    text = EXAMPLE_CONFIG.read_text()
    text = text.replace("../demo-output/results.sqlite3", str(tmp / "results.sqlite3"))
    text = text.replace("../demo-output/world-state.json", str(state_path))
    text = text.replace("scene: scenes/grundfos_cell.yaml", f"scene: {SCENE}")
    path = tmp / "cell.yaml"
    path.write_text(text + extra)
    return path


@contextlib.contextmanager
def _live_server(config: Path) -> Iterator[int]:
    """A VisionServer with the configuration's catalog, in a thread; yields its port."""
    runtime = CellRuntime(config)
    try:
        with server_in_thread(runtime.catalog, results=runtime.results, workers=2) as server:
            yield server.port
    finally:
        runtime.close()


@pytest.fixture(scope="session")
def cell_config() -> Callable[..., Path]:
    """``cell_config(tmp, state_path, extra="")``: a copy of the example cell's configuration."""
    return _cell_config


@pytest.fixture(scope="session")
def live_server() -> Callable[[Path], contextlib.AbstractContextManager[int]]:
    """``with live_server(config) as port``: a real server on 127.0.0.1."""
    return _live_server
