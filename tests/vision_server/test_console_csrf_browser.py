"""Cross-site requests in a real browser (headless Chromium): a page of another origin on the
same host (another port: SameSite ignores ports, so the operator's session cookie goes along)
tries to save a lower threshold and to answer with the console's session, as an attacker's page
open in the operator's browser would. The console refuses them (403 CROSS_SITE) and the
configuration file is unchanged.

The attacks are the classic ones: an HTML form posting JSON-looking text as ``text/plain``, a
multipart form, and ``fetch`` in ``no-cors`` mode (a simple request). A JSON ``fetch`` needs a
CORS preflight, which the console never grants."""

from __future__ import annotations

import http.server
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from browser import headless_chromium
from console_server import TOKEN, RunningConsole, console_server

selenium = pytest.importorskip("selenium")
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

pytestmark = pytest.mark.slow
WAIT_S = 30.0  # only bounds a hang


def _attacker_pages(console: str) -> dict[str, str]:
    """The attacker's pages, by path; each attacks ``console`` (its origin) as it loads."""
    save = f"{console}api/inspections/magnet_check/save"
    json_field = '{"options": {"threshold": 1}, "pad": "'
    return {
        "/form-text": f"""<!doctype html><form id=f method=POST enctype="text/plain"
            action="{save}"><input name='{json_field}' value='"}}'></form>
            <script>document.getElementById("f").submit();</script>""",
        "/form-multipart": f"""<!doctype html><form id=f method=POST
            enctype="multipart/form-data" action="{save}">
            <input name=options value='{{"threshold": 1}}'></form>
            <script>document.getElementById("f").submit();</script>""",
        "/fetch": f"""<!doctype html><script>
            fetch("{save}", {{method: "POST", mode: "no-cors", credentials: "include",
              headers: {{"Content-Type": "text/plain"}},
              body: JSON.stringify({{options: {{threshold: 1}}}})}})
              .then(() => {{ document.title = "sent"; }}, () => {{ document.title = "failed"; }});
            </script>""",
    }


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("csrf")) as running:
        yield running


@pytest.fixture(scope="module")
def attacker(cell: RunningConsole) -> Iterator[str]:
    """An HTTP server on another port of the same host, serving the attacker's pages."""
    pages = _attacker_pages(cell.url)

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the standard library's name
            body = pages.get(self.path, "not found").encode()
            self.send_response(200 if self.path in pages else 404)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


@pytest.fixture(scope="module")
def signed_in(cell: RunningConsole) -> Iterator[WebDriver]:
    """A browser signed in to the console (its session cookie set, as the operator's is)."""
    with headless_chromium() as driver:
        driver.get(cell.url)
        status = driver.execute_async_script(
            """const done = arguments[arguments.length - 1];
            fetch("/api/login", {method: "POST", headers: {"Content-Type": "application/json",
              "X-Cellvision": "console"}, body: JSON.stringify({token: arguments[0]})})
              .then((r) => done(r.status), (e) => done(String(e)));""",
            TOKEN,
        )
        assert status == 200
        yield driver


def _threshold_unchanged(cell: RunningConsole, before: str) -> bool:
    return cell.config.read_text(encoding="utf-8") == before


@pytest.mark.parametrize("page", ["/form-text", "/form-multipart"])
def test_a_form_of_another_origin_cannot_save(
    cell: RunningConsole, attacker: str, signed_in: WebDriver, page: str
) -> None:
    before = cell.config.read_text(encoding="utf-8")
    signed_in.get(attacker + page)
    # The form navigates the browser to the console's answer.
    WebDriverWait(signed_in, WAIT_S).until(
        lambda d: "CROSS_SITE" in d.page_source or "config_hash" in d.page_source,
        "timed out waiting for the console's answer to the form",
    )
    assert "CROSS_SITE" in signed_in.page_source
    assert _threshold_unchanged(cell, before)


def test_a_simple_fetch_of_another_origin_cannot_save(
    cell: RunningConsole, attacker: str, signed_in: WebDriver, tmp_path: Path
) -> None:
    before = cell.config.read_text(encoding="utf-8")
    signed_in.get(attacker + "/fetch")
    WebDriverWait(signed_in, WAIT_S).until(
        lambda d: d.title in ("sent", "failed"), "timed out waiting for the fetch"
    )
    assert _threshold_unchanged(cell, before)
    # The session itself is fine: the console's own page saves (same origin, its header).
    signed_in.get(cell.url)
    status = signed_in.execute_async_script(
        """const done = arguments[arguments.length - 1];
        fetch("/api/inspections/magnet_check/save", {method: "POST",
          headers: {"Content-Type": "application/json", "X-Cellvision": "console"},
          body: JSON.stringify({options: {threshold: 77}})})
          .then((r) => done(r.status), (e) => done(String(e)));"""
    )
    assert status == 200
    assert not _threshold_unchanged(cell, before)
