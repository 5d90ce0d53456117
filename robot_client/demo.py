"""``make demo``: start a vision server on loopback, run a client round trip against it, stop it.

(The full demo of the paper's cell, on the simulated cell, replaces this round trip when the
skills land.) Exits 0 only if every step succeeded.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import signal
import subprocess
import sys
import time

import numpy as np
from rich.console import Console
from rich.table import Table

from protocol import CellvisionError, ImageEncoding, UnknownInspection

from .client import VisionClient


def start_server() -> tuple[subprocess.Popen[str], int]:
    """Start ``vision-server serve --port 0`` and read the port it bound from its first line."""
    process = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--host", "127.0.0.1", "--port", "0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None
    line = process.stdout.readline()
    match = re.search(r"listening on [^\s:]+:(\d+)", line)
    if not match:
        process.kill()
        raise RuntimeError(f"the server did not start: {line!r}")
    return process, int(match.group(1))


def stop_server(process: subprocess.Popen[str]) -> int:
    process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()


async def round_trip(port: int, console: Console) -> list[tuple[str, bool, str]]:
    steps: list[tuple[str, bool, str]] = []
    bright = np.full((768, 1024), 180, np.uint8)
    dark = np.full((768, 1024), 20, np.uint8)
    async with VisionClient("127.0.0.1", port) as client:
        welcome = client.welcome
        assert welcome is not None
        steps.append(
            (
                "handshake",
                True,
                f"{welcome.server_name} {welcome.server_version}, "
                f"protocol {welcome.version[0]}.{welcome.version[1]}",
            )
        )
        rtt = await client.ping()
        steps.append(("ping", True, f"{rtt * 1000:.2f} ms"))
        names = [i["name"] for i in await client.list_inspections()]
        steps.append(("list inspections", "brightness" in names, ", ".join(names)))
        t0 = time.perf_counter()
        result = await client.inspect("brightness", bright)
        steps.append(
            (
                "inspect bright image (expect pass)",
                result.passed,
                f"mean {result.data['value']:.1f}, {(time.perf_counter() - t0) * 1000:.1f} ms",
            )
        )
        result = await client.inspect("brightness", dark, encoding=ImageEncoding.PNG)
        steps.append(
            (
                "inspect dark PNG image (expect fail)",
                not result.passed,
                f"mean {result.data['value']:.1f}",
            )
        )
        try:
            await client.inspect("no_such_inspection", bright)
            steps.append(("unknown inspection (expect typed error)", False, "no error"))
        except UnknownInspection as exc:
            steps.append(("unknown inspection (expect typed error)", True, exc.code.name))
        answers = await asyncio.gather(*(client.ping(str(i)) for i in range(20)))
        steps.append(("20 pipelined pings", len(answers) == 20, "all matched by id"))
    return steps


def main() -> int:
    console = Console()
    console.print("[bold]cellvision demo[/]: server on loopback, client round trip")
    process, port = start_server()
    console.print(f"vision server started on 127.0.0.1:{port} (pid {process.pid})")
    steps: list[tuple[str, bool, str]] = []
    try:
        steps = asyncio.run(round_trip(port, console))
    except (CellvisionError, OSError) as exc:
        steps.append(("round trip", False, f"{type(exc).__name__}: {exc}"))
    finally:
        code = stop_server(process)
        steps.append(("server stopped cleanly", code == 0, f"exit code {code}"))
    table = Table(title="Demo")
    table.add_column("step")
    table.add_column("ok")
    table.add_column("detail")
    for name, ok, detail in steps:
        table.add_row(name, "[green]yes[/]" if ok else "[red]NO[/]", detail)
    console.print(table)
    ok = all(ok for _, ok, _ in steps)
    console.print("[green]demo succeeded[/]" if ok else "[red]demo failed[/]")
    return 0 if ok else 1


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
