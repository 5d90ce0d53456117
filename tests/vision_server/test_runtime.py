"""Configuration at run time: reload keeps connections and unchanged cameras, refuses a broken
file and keeps the old configuration; SIGHUP and RELOAD both trigger it; the CLI commands."""

from __future__ import annotations

import asyncio
import json
import re
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from protocol import (
    ConfigInvalid,
    ImageEncoding,
    InvalidArgument,
    Reload,
    Reloaded,
    UnknownInspection,
    array_from_payload,
)
from robot_client import VisionClient
from vision_server.commands.admin import call
from vision_server.config import ConfigError
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import CellRuntime

CONFIG = """\
server: {{port: 0}}
results: {{path: results.sqlite3, store_images: all}}
cameras:
  tool: {{source: request}}
  replay: {{source: folder, path: frames}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: {low}}}
  - {{name: replayed, type: presence, camera: replay, measure: mean_intensity, min: 0}}
{extra}"""


def write_config(directory: Path, *, low: float = 100, extra: str = "") -> Path:
    frames = directory / "frames"
    frames.mkdir(exist_ok=True)
    for i in range(3):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((48, 64), 50 * (i + 1), np.uint8))
    path = directory / "cell.yaml"
    path.write_text(CONFIG.format(low=low, extra=extra), encoding="utf-8")
    return path


def run(coro: object) -> object:
    return asyncio.run(coro)  # type: ignore[arg-type]


def test_reload_swaps_inspections_keeps_unchanged_cameras_and_refuses_broken_files(
    tmp_path: Path,
) -> None:
    path = write_config(tmp_path)
    runtime = CellRuntime(path)
    try:
        replay_before = runtime.catalog.cameras["replay"]
        old_hash = runtime.catalog.config_hash
        write_config(tmp_path, low=10, extra="  - {name: new_one, type: qr, camera: tool}\n")
        catalog = runtime.reload()
        assert "new_one" in catalog.inspections
        assert catalog.config_hash != old_hash
        assert catalog.cameras["replay"] is replay_before, "an unchanged camera is kept open"

        path.write_text(path.read_text() + "  - {name: broken, type: qr, camera: nope}\n")
        with pytest.raises(ConfigError, match=r"cell.yaml:\d+ inspections\[3\]"):
            runtime.reload()
        assert runtime.catalog is catalog, "the old configuration stays"
    finally:
        runtime.close()


def test_results_of_served_inspections_are_logged(tmp_path: Path) -> None:
    runtime = CellRuntime(write_config(tmp_path))

    async def body() -> None:
        server = VisionServer(runtime.catalog, ServerSettings(port=0), results=runtime.results)
        async with server, VisionClient("127.0.0.1", server.port) as client:
            ok = await client.inspect("bright", np.full((32, 32), 200, np.uint8))
            bad = await client.inspect("bright", np.full((32, 32), 20, np.uint8))
            replayed = await client.inspect("replayed")
            assert (ok.passed, bad.passed, replayed.passed) == (True, False, True)

    try:
        run(body())
        assert runtime.results is not None
        rows = runtime.results.query(newest_first=False)
        assert [(r.inspection, r.passed) for r in rows] == [
            ("bright", True),
            ("bright", False),
            ("replayed", True),
        ]
        assert rows[2].camera == "replay"
        assert all(r.image_path is not None and r.image_path.is_file() for r in rows)
    finally:
        runtime.close()


def test_reload_over_the_protocol(tmp_path: Path) -> None:
    path = write_config(tmp_path)
    runtime = CellRuntime(path)

    async def body() -> None:
        server = VisionServer(runtime.catalog, ServerSettings(port=0), reloader=runtime.reload)
        async with server, VisionClient("127.0.0.1", server.port) as client:
            with pytest.raises(UnknownInspection):
                await client.inspect("late", np.zeros((64, 64), np.uint8))
            write_config(tmp_path, extra="  - {name: late, type: qr, camera: tool}\n")
            answer = await asyncio.to_thread(call, "127.0.0.1", server.port, Reload)
            assert isinstance(answer, Reloaded)
            assert "late" in {i["name"] for i in answer.inspections}
            # The connection opened before the reload is still there and sees the new config.
            result = await client.inspect("late", np.zeros((64, 64), np.uint8))
            assert not result.passed
            path.write_text("inspections: [oops\n")
            with pytest.raises(ConfigInvalid, match="cell.yaml"):
                await asyncio.to_thread(call, "127.0.0.1", server.port, Reload)
            assert (await client.inspect("late", np.zeros((64, 64), np.uint8))).inspection == "late"

    try:
        run(body())
    finally:
        runtime.close()


def test_reload_without_a_configuration_is_refused() -> None:
    from vision_server.service import builtin_catalog

    async def body() -> None:
        async with VisionServer(builtin_catalog(), ServerSettings(port=0)) as server:
            with pytest.raises(InvalidArgument, match="without a configuration file"):
                await asyncio.to_thread(call, "127.0.0.1", server.port, Reload)

    run(body())


def vision_server(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "vision_server", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd,
        check=False,
    )


async def _line_with(text: str, stream: Any) -> str:
    """The first line of ``stream`` that contains ``text`` (other lines a server logs may come
    first); empty at the end of the stream."""
    while True:
        line: str = await asyncio.to_thread(stream.readline)
        if not line or text in line:
            return line


def test_sighup_reloads_and_a_broken_file_keeps_the_old_config(tmp_path: Path) -> None:
    path = write_config(tmp_path)
    process = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--config", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        assert process.stderr is not None
        port = int(re.search(r":(\d+)$", process.stdout.readline().strip()).group(1))  # type: ignore[union-attr]

        async def body() -> None:
            async with VisionClient("127.0.0.1", port) as client:
                write_config(tmp_path, extra="  - {name: hup, type: qr, camera: tool}\n")
                process.send_signal(signal.SIGHUP)
                assert "reloaded" in await _line_with("reloaded", process.stdout)
                names = {i["name"] for i in await client.list_inspections()}
                assert "hup" in names
                path.write_text("inspections: {not: [a list}\n")
                process.send_signal(signal.SIGHUP)
                line = await _line_with("reload refused", process.stderr)
                assert "reload refused" in line
                assert "cell.yaml" in line
                assert "hup" in {i["name"] for i in await client.list_inspections()}
                await client.ping()

        run(body())
    finally:
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=20) == 0


def test_check_config_cli(tmp_path: Path) -> None:
    good = vision_server("check-config", str(write_config(tmp_path)), "--json")
    assert good.returncode == 0, good.stderr
    summary = json.loads(good.stdout)
    assert summary["valid"] is True
    assert {i["name"] for i in summary["inspections"]} == {"bright", "replayed"}
    bad_path = tmp_path / "bad.yaml"
    bad_path.write_text("server:\n  port: seven\n")
    bad = vision_server("check-config", str(bad_path))
    assert bad.returncode == 2
    assert "bad.yaml:2 server -> port: expected an integer" in bad.stderr


def test_run_cli_offline_with_overlay_and_results_cli(tmp_path: Path) -> None:
    path = write_config(tmp_path)
    image = tmp_path / "img.png"
    cv2.imwrite(str(image), np.full((40, 40), 180, np.uint8))
    overlay = tmp_path / "overlay.png"
    done = vision_server(
        "run",
        "--config",
        str(path),
        "bright",
        "--image",
        str(image),
        "--json",
        "--overlay",
        str(overlay),
    )
    assert done.returncode == 0, done.stderr
    answer = json.loads(done.stdout)
    assert answer["verdict"] == "pass"
    assert answer["data"]["value"] == pytest.approx(180.0)
    picture = cv2.imread(str(overlay))
    assert picture is not None
    assert picture.shape[:2] == (40, 40)
    dark = tmp_path / "dark.png"
    cv2.imwrite(str(dark), np.full((40, 40), 10, np.uint8))
    failed = vision_server("run", "--config", str(path), "bright", "--image", str(dark))
    assert failed.returncode == 1  # the fail verdict
    missing = vision_server("run", "--config", str(path), "nope", "--image", str(dark))
    assert missing.returncode == 2
    assert "no inspection named 'nope'" in missing.stderr


def test_ping_cli_fails_cleanly_when_nothing_listens() -> None:
    done = vision_server("ping", "--server", "127.0.0.1:9", "--timeout", "1")
    assert done.returncode == 3  # a connection error
    assert "127.0.0.1:9" in done.stderr


def test_capture_returns_distinct_frames_from_a_server_camera(tmp_path: Path) -> None:
    runtime = CellRuntime(write_config(tmp_path))

    async def body() -> None:
        server = VisionServer(runtime.catalog, ServerSettings(port=0))
        async with server, VisionClient("127.0.0.1", server.port) as client:
            frames = await client.capture("replay", count=3)
            values = [int(array_from_payload(p).mean()) for p in frames.images]
            assert values == [50, 100, 150]  # three distinct files, in order
            assert len(frames.timestamps) == 3
            png = await client.capture("replay", count=1, encoding=ImageEncoding.PNG)
            assert png.images[0].encoding is ImageEncoding.PNG
            with pytest.raises(InvalidArgument, match="has no depth"):
                await client.capture("replay", depth=True)

    try:
        run(body())
    finally:
        runtime.close()


def test_results_cli_lists_what_was_served(tmp_path: Path) -> None:
    path = write_config(tmp_path)
    runtime = CellRuntime(path)

    async def body() -> None:
        server = VisionServer(runtime.catalog, ServerSettings(port=0), results=runtime.results)
        async with server, VisionClient("127.0.0.1", server.port) as client:
            await client.inspect("bright", np.full((16, 16), 200, np.uint8))
            await client.inspect("bright", np.full((16, 16), 10, np.uint8))

    try:
        run(body())
    finally:
        runtime.close()
    done = vision_server("results", "--config", str(path), "--json")
    assert done.returncode == 0, done.stderr
    rows = [json.loads(line) for line in done.stdout.splitlines()]
    assert [r["verdict"] for r in rows] == ["fail", "pass"]  # newest first
    failed = vision_server("results", "--config", str(path), "--failed", "--json")
    assert len(failed.stdout.splitlines()) == 1
