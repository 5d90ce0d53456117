"""The real vision server with its web console, for the console's API and browser tests.

:func:`console_server` copies the example cell (``examples/cell.yaml``: the simulated QC camera,
``magnet_check``, ...) into a temporary folder with both ports 0, the console enabled and a
token, and runs ``App`` (the server ``vision-server serve`` runs) on its own event loop in a
thread, with the configuration file's runtime, so that saving and reloading are the real ones.

Importable as ``console_server`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import asyncio
import contextlib
import http.cookiejar
import json
import threading
import urllib.error
import urllib.request
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vision_server.app import App
from vision_server.service import CellRuntime

REPO_ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = REPO_ROOT / "examples" / "cell.yaml"
TOKEN = "console-test-token-0123456789"


def example_config(
    folder: Path, *, token: str | None = TOKEN, extra_server: str = "", drop: tuple[str, ...] = ()
) -> Path:
    """The example cell as ``folder/cell.yaml``: ports 0, the console on, results in
    ``folder``, the scene by absolute path."""
    text = EXAMPLE.read_text(encoding="utf-8")
    # The server keys a test sets replace the example's.
    text = "".join(
        line
        for line in text.splitlines(keepends=True)
        if not any(line.startswith(f"  {key}:") for key in drop)
    )
    text = text.replace(
        "scenes/grundfos_cell.yaml", str(EXAMPLE.parent / "scenes/grundfos_cell.yaml")
    )
    text = text.replace("../demo-output/", f"{folder}/")
    text = text.replace("  port: 7878\n", "  port: 0\n" + extra_server)
    if token is not None:
        text = text.replace(
            "  name: grundfos-cell\n", f"  name: grundfos-cell\n  auth_token: {token}\n"
        )
    start = text.find("\nconsole:")
    if start >= 0:  # the example's own console section: replaced by the test's
        end = text.find("\n\n", start + 1)
        text = text[:start] + text[end:]
    text = text.replace(
        "\ncameras:", "\nconsole:\n  enabled: true\n  port: 0\n  max_view_fps: 30\n\ncameras:", 1
    )
    path = folder / "cell.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@dataclass
class RunningConsole:
    """A running server: ``url`` of its console, its ``app``, ``config`` file and loop."""

    app: App
    config: Path
    loop: asyncio.AbstractEventLoop
    url: str = ""
    runtime: CellRuntime | None = field(default=None, repr=False)

    def call(self, fn: Callable[[], Any]) -> Any:
        """Run ``fn`` on the server's event loop and return its result."""

        async def run() -> Any:
            return fn()

        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(10.0)


@contextlib.contextmanager
def console_server(
    folder: Path, *, token: str | None = TOKEN, **server: Any
) -> Iterator[RunningConsole]:
    extra = "".join(f"  {k}: {v}\n" for k, v in server.items())
    config = example_config(folder, token=token, extra_server=extra, drop=tuple(server))
    with running_cell(config) as running:
        yield running


@contextlib.contextmanager
def running_cell(config: Path) -> Iterator[RunningConsole]:
    """The server (``App``, console on) of configuration file ``config``, on its own event loop
    in a thread, as ``vision-server serve`` wires it; stopped and closed afterwards."""
    runtime = CellRuntime(config)
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="console-server", daemon=True)
    thread.start()

    async def make() -> App:
        return App(
            runtime.catalog,
            runtime.config.server,
            results=runtime.results,
            reloader=runtime.reload,
            console=runtime.config.console,
            line=runtime.config.line,
            modbus=runtime.config.modbus,
            config_path=config,
        )

    app = asyncio.run_coroutine_threadsafe(make(), loop).result(10.0)
    try:
        asyncio.run_coroutine_threadsafe(app.start(), loop).result(20.0)
        assert app.http is not None
        yield RunningConsole(app, config, loop, app.http.url, runtime)
    finally:
        with contextlib.suppress(RuntimeError):
            asyncio.run_coroutine_threadsafe(app.stop(), loop).result(30.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()
        runtime.close()


# ----------------------------------------------------------------------------- a client


@dataclass
class Reply:
    status: int
    headers: Any
    body: bytes

    def json(self) -> Any:
        return json.loads(self.body)


class Browserless:
    """A urllib client with a cookie jar: what a browser would send, without one."""

    def __init__(self, base: str) -> None:
        self.base = base.rstrip("/")
        self.jar = http.cookiejar.CookieJar()
        self.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(self.jar))

    def request(
        self,
        method: str,
        path: str,
        body: bytes | None = None,
        headers: dict[str, str] | None = None,
    ) -> Reply:
        headers = dict(headers or {})
        if method not in ("GET", "HEAD"):  # as the console's page does (static/js/api.js)
            headers.setdefault("X-Cellvision", "console")
        req = urllib.request.Request(self.base + path, data=body, method=method, headers=headers)
        try:
            with self.opener.open(req, timeout=30) as resp:
                return Reply(resp.status, resp.headers, resp.read())
        except urllib.error.HTTPError as exc:
            return Reply(exc.code, exc.headers, exc.read())

    def get(self, path: str) -> Reply:
        return self.request("GET", path)

    def post_json(self, path: str, value: Any) -> Reply:
        return self.request(
            "POST", path, json.dumps(value).encode(), {"Content-Type": "application/json"}
        )

    def login(self, token: str = TOKEN) -> Reply:
        return self.post_json("/api/login", {"token": token})

    def try_(self, name: str, spec: dict[str, Any], image: bytes | None = None) -> Reply:
        body, content_type = multipart(
            {"request": json.dumps(spec).encode()}, {"image": image} if image is not None else {}
        )
        return self.request(
            "POST", f"/api/inspections/{name}/try", body, {"Content-Type": content_type}
        )


def multipart(fields: dict[str, bytes], files: dict[str, bytes]) -> tuple[bytes, str]:
    """A multipart/form-data body and its content type."""
    boundary = uuid.uuid4().hex
    out = bytearray()
    for name, value in fields.items():
        out += f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n'.encode()
        out += b"Content-Type: application/json\r\n\r\n" + value + b"\r\n"
    for name, value in files.items():
        out += (
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="x.png"\r\n'
            "Content-Type: application/octet-stream\r\n\r\n"
        ).encode()
        out += value + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out), f"multipart/form-data; boundary={boundary}"
