"""The cell the MQTT tests (tests/vision_server/mqtt/) serve: one inspection on images sent with the
verdict the test chooses with the image's grey level, and a result log (so that each RESULT
carries the row id its MQTT payload repeats)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np

from protocol import schema
from robot_client import VisionClient
from vision_server.app import App
from vision_server.config import ServerSettings
from vision_server.service import CellRuntime

CONFIG = """\
server: {{port: 0, name: line-7}}
results: {{path: results.sqlite3}}
cameras:
  tool: {{source: request}}
inspections:
  - name: bright
    type: presence
    camera: tool
    measure: mean_intensity
    min: 100
mqtt:
  enabled: true
  port: {port}
  topic_prefix: plant/hall-2
  reconnect_min_s: 0.1
  reconnect_max_s: 0.5
{extra}"""
RESULTS = "plant/hall-2/line-7/results/+"
STATE = "plant/hall-2/line-7/state"
PASSING = np.full((24, 32), 200, np.uint8)
FAILING = np.full((24, 32), 20, np.uint8)


def write_cell(directory: Path, port: int, extra: str = "") -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "cell.yaml"
    path.write_text(CONFIG.format(port=port, extra=extra), encoding="utf-8")
    return path


@contextlib.asynccontextmanager
async def serving(path: Path) -> AsyncIterator[App]:
    runtime = CellRuntime(path)
    app = App(
        runtime.catalog,
        ServerSettings(**{**runtime.config.server.__dict__, "workers": 2}),
        results=runtime.results,
        mqtt=runtime.config.mqtt,
        console=runtime.config.console,
        config_path=path,
    )
    try:
        async with app:
            yield app
    finally:
        runtime.close()


async def inspect(client: VisionClient, passed: bool) -> tuple[int, bool]:
    """One INSPECT; (the RESULT's result_id, its verdict)."""
    result = await client.inspect("bright", PASSING if passed else FAILING)
    assert result.result_id is not None
    return result.result_id, result.passed


def valid_results(payloads: list[dict[str, object]]) -> dict[int, dict[str, object]]:
    """Each payload checked against protocol/schema/mqtt/result.json, by result_id."""
    for payload in payloads:
        schema.validate_mqtt("result", payload)
    return {int(p["result_id"]): p for p in payloads}  # type: ignore[call-overload]
