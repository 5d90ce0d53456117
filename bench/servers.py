"""Servers under test, each in its own process on 127.0.0.1 (as the cell PC would run them):

- ``cellvision``: :class:`vision_server.VisionServer` with the bench catalog (bench/cell.py),
  default settings except the port. ``cellvision_idle``: the same with ``main_lane_policy:
  idle`` (section 2c compares the two). ``cellvision_asyncio``, ``cellvision_uvloop``: the
  same on that event loop (``server: event_loop``); ``cellvision`` runs on the default one, and
  sections 1 and 2 compare it with the other.
- ``echo``: the floor, a bare asyncio socket. It reads a frame's 24-byte header and body (the
  same bytes a cellvision client sends) and answers with as many bytes as the header's request
  id field says (the client puts there the size of the real answer), so the same bytes cross
  the socket in both directions, with no protocol work at either end.
- ``http``: what a team would write instead: aiohttp, JSON bodies, images as base64.
  ``POST /inspect/NAME`` with ``{"image": {"data", "width", "height", "encoding"}, "depth":
  [...], "deadline_ms": ...}`` answers ``{"inspection", "verdict", "data", "timing"}``;
  ``GET /ping``. It is a front-end of its own over the same inspection service as the
  cellvision server (admission and BUSY, deadlines from arrival, image checks, the worker
  pool): parse JSON, call the service, render JSON, and map error codes to HTTP statuses in
  one table (:data:`HTTP_STATUS`).

``python -m bench.servers KIND [--config PATH]`` prints one JSON line (``port``, ...) when it
listens and stops when its standard input closes. :class:`ServerProcess` runs one.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import IO, Any

import numpy as np

from vision_server.process import EVENT_LOOPS, PROCESS_ENV, loop_factory

from .common import ROOT, Skip

HOST = "127.0.0.1"
PROCESS_INSPECTIONS = ("cap_locate", "station_pose")
"""Run in worker processes by the cellvision server (``server: process_inspections``): the
inspections that section 2b's rule finds holding the GIL on the development machine (2 threads
made 1.40-1.52x and 1.33-1.37x one thread's calls over three runs)."""
READ_LIMIT = 256 * 1024  # the cellvision server's read chunk


class ServerProcess:
    """A server subprocess: ``info`` is its announcement (``port``, ...). Stopped by closing
    its standard input (it exits by itself); killed by its own pid only if it hangs."""

    def __init__(self, kind: str, workdir: Path, *args: str, module: str = "bench.servers") -> None:
        """``python -m MODULE KIND ARGS...``; another ``module`` (bench.console_server) takes
        ``args`` alone (``kind`` names its log)."""
        self.kind = kind
        self._log_path = workdir / f"server-{kind}.log"
        self._log: IO[bytes] = self._log_path.open("wb")
        command = [kind, *args] if module == "bench.servers" else list(args)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, *command],
            cwd=ROOT,
            # The malloc settings `vision-server serve` starts itself with, so that the bench
            # measures the server as it runs in a cell.
            env={**PROCESS_ENV, **os.environ},
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._log,
        )
        self._info: dict[str, Any] | None = None

    @property
    def info(self) -> dict[str, Any]:
        """The server's announcement; waits for it (up to a minute) the first time."""
        if self._info is None:
            self._info = self._announcement(timeout_s=60.0)
        return self._info

    @property
    def port(self) -> int:
        return int(self.info["port"])

    def _announcement(self, timeout_s: float) -> dict[str, Any]:
        out = self.proc.stdout
        assert out is not None
        lines: list[bytes] = []
        reader = threading.Thread(target=lambda: lines.append(out.readline()), daemon=True)
        reader.start()
        reader.join(timeout_s)
        if not lines or not lines[0]:
            self.stop()
            tail = self._log_path.read_text(errors="replace")[-2000:]
            raise Skip(f"the {self.kind} server did not start: {tail.strip() or 'no output'}")
        info: dict[str, Any] = json.loads(lines[0])
        return info

    def cpu_seconds(self) -> float:
        """User + system CPU time the server process has used so far."""
        try:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return float("nan")
        import os

        ticks = os.sysconf("SC_CLK_TCK")
        return (int(fields[11]) + int(fields[12])) / ticks

    def stop(self) -> None:
        if self.proc.poll() is None:
            if self.proc.stdin is not None:
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout=20.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10.0)
        self._log.close()


# --- the processes ------------------------------------------------------------------------------


def _announce(info: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(info) + "\n")
    sys.stdout.flush()


def _stdin_closed(loop: asyncio.AbstractEventLoop) -> asyncio.Event:
    done = asyncio.Event()

    def wait() -> None:
        sys.stdin.buffer.read()
        loop.call_soon_threadsafe(done.set)

    threading.Thread(target=wait, daemon=True).start()
    return done


async def _serve_cellvision(config: Path | None, policy: str = "nice") -> None:
    from vision_server import ServerSettings, VisionServer

    from .cell import load_catalog

    bench = load_catalog(config)
    chosen = tuple(n for n in PROCESS_INSPECTIONS if n in bench.catalog.inspections)
    server = VisionServer(
        bench.catalog,
        ServerSettings(port=0, process_inspections=chosen, main_lane_policy=policy),
    )
    await server.start()
    done = _stdin_closed(asyncio.get_running_loop())
    _announce(
        {
            "port": server.port,
            "inspections": sorted(bench.catalog.inspections),
            "problem": bench.problem,
            "workers": server.settings.workers,
            "queue_depth": server.settings.queue_depth,
            "max_in_flight": server.settings.max_in_flight,
            "process_inspections": list(chosen),
            "main_lane_nice": server.settings.main_lane_nice,
            "main_lane_policy": server.settings.main_lane_policy,
        }
    )
    await done.wait()
    await server.stop()


async def _serve_echo() -> None:
    replies: dict[int, bytes] = {}

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                header = await reader.readexactly(24)
                body = int.from_bytes(header[20:24], "little")
                size = int.from_bytes(header[12:16], "little")
                if body:
                    await reader.readexactly(body)
                reply = replies.get(size)
                if reply is None:
                    reply = replies.setdefault(size, bytes(size))
                writer.write(reply)
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(handle, HOST, 0, limit=READ_LIMIT)
    done = _stdin_closed(asyncio.get_running_loop())
    _announce({"port": server.sockets[0].getsockname()[1]})
    await done.wait()
    server.close()


def _array(spec: dict[str, Any]) -> Any:
    raw = base64.b64decode(spec["data"])
    width, height, encoding = int(spec["width"]), int(spec["height"]), spec["encoding"]
    if encoding == "gray8":
        return np.frombuffer(raw, np.uint8).reshape(height, width)
    if encoding == "bgr8":
        return np.frombuffer(raw, np.uint8).reshape(height, width, 3)
    if encoding == "depth16":
        return np.frombuffer(raw, "<u2").reshape(height, width)
    raise ValueError(f"unknown encoding {encoding!r}")


HTTP_STATUS = {
    "BUSY": 503,
    "DEADLINE_EXCEEDED": 504,
    "UNKNOWN_INSPECTION": 404,
    "UNKNOWN_CAMERA": 404,
    "BAD_IMAGE": 400,
    "IMAGE_TOO_LARGE": 413,
    "INVALID_ARGUMENT": 400,
    "CAMERA_UNAVAILABLE": 503,
    "INSPECTION_FAILED": 422,
}
"""The HTTP front-end's one table from the service's error codes to statuses (else 500)."""


async def _serve_http(config: Path | None) -> None:
    from aiohttp import web

    from protocol import CellvisionError
    from vision_server.service import Images, InspectionService, InspectRequest, deadline_after

    from .cell import load_catalog

    service = InspectionService(load_catalog(config).catalog)

    async def ping(request: web.Request) -> web.Response:
        return web.json_response({"ok": True})

    async def inspect(request: web.Request) -> web.Response:
        body = await request.json()
        arrived = time.monotonic()  # the whole request is in (SPEC §6.1's rule, kept here)
        try:
            images = Images(_array(body["image"]), tuple(_array(d) for d in body.get("depth", ())))
        except (KeyError, ValueError, TypeError) as exc:
            return web.json_response(
                {"error": {"code": "BAD_IMAGE", "message": str(exc)}}, status=400
            )
        wanted = InspectRequest(
            request.match_info["name"],
            images,
            arrived=arrived,
            deadline=deadline_after(arrived, body.get("deadline_ms")),
            peer=str(request.remote),
        )
        try:
            reply = await service.inspect(wanted)
        except CellvisionError as exc:
            error = {"code": exc.code.name, "message": exc.message}
            return web.json_response({"error": error}, status=HTTP_STATUS.get(exc.code.name, 500))
        return web.json_response(
            {
                "inspection": reply.inspection,
                "verdict": "pass" if reply.passed else "fail",
                "data": reply.data,
                "timing": reply.timing,
            }
        )

    app = web.Application(client_max_size=64 * 1024 * 1024)
    app.router.add_get("/ping", ping)
    app.router.add_post("/inspect/{name}", inspect)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, HOST, 0)
    await site.start()
    done = _stdin_closed(asyncio.get_running_loop())
    _announce({"port": runner.addresses[0][1]})
    await done.wait()
    await runner.cleanup()
    service.close()


def default_loop() -> str:
    """The event loop ``serve`` runs on by default (``server: event_loop``)."""
    from vision_server import ServerSettings

    return ServerSettings().event_loop


def other_loop() -> str:
    """The loop the benchmarks compare the default with."""
    return next(name for name in EVENT_LOOPS if name != default_loop())


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.servers")
    parser.add_argument(
        "kind",
        choices=["cellvision", "cellvision_idle", *(f"cellvision_{n}" for n in EVENT_LOOPS)]
        + ["echo", "http"],
    )
    parser.add_argument("--config", type=Path, default=None)
    parser.add_argument("--loop", choices=EVENT_LOOPS, default=default_loop())
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    serving: Coroutine[Any, Any, None]
    loop = args.loop
    if args.kind == "cellvision":
        serving = _serve_cellvision(args.config)
    elif args.kind.startswith("cellvision_") and args.kind[len("cellvision_") :] in EVENT_LOOPS:
        serving = _serve_cellvision(args.config)
        loop = args.kind[len("cellvision_") :]
    elif args.kind == "cellvision_idle":
        serving = _serve_cellvision(args.config, "idle")
    elif args.kind == "echo":
        serving = _serve_echo()
    else:
        serving = _serve_http(args.config)
    # The loop `serve` would run with `server: event_loop` (section 1 measures both).
    with asyncio.Runner(loop_factory=loop_factory(loop)) as runner:
        runner.run(serving)


if __name__ == "__main__":
    main()
