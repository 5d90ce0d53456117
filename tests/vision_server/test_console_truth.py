"""The web console tells the truth (docs/console.md): real HTTP on loopback, port 0, against
the real server with the example cell.

- a console try lands in the result log only as a try (its options in its row, marked in the
  API and the CLI) and counts in no production figure (/api/stats, Prometheus);
"""

from __future__ import annotations

import io
from collections.abc import Iterator

import pytest
from console_server import Browserless, RunningConsole, console_server
from rich.console import Console

from vision_server.results_cli import results_command


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        yield running


@pytest.fixture
def client(server: RunningConsole) -> Browserless:
    c = Browserless(server.url)
    assert c.login().status == 200
    return c


def _metric(text: str, inspection: str, verdict: str) -> float:
    prefix = f'cellvision_inspections_total{{inspection="{inspection}",verdict="{verdict}"}} '
    for line in text.splitlines():
        if line.startswith(prefix):
            return float(line[len(prefix) :])
    return 0.0


def test_a_try_is_recorded_only_as_a_try(server: RunningConsole, client: Browserless) -> None:
    before = client.get("/api/stats?inspection=magnet_check&window_s=3600").json()
    metrics_before = client.get("/metrics").body.decode()
    # A wrong ROI (a dark corner of the frame) makes the failing part PASS.
    options = {"roi": [10, 10, 50, 60]}
    reply = client.try_("magnet_check", {"source": "camera", "options": options})
    assert reply.status == 200, reply.body
    assert reply.json()["verdict"] == "pass"

    rows = client.get("/api/results?inspection=magnet_check&limit=1").json()["results"]
    assert rows[0]["peer"].startswith("console ")
    assert rows[0]["try"] is True
    detail = client.get(f"/api/results/{rows[0]['id']}").json()
    assert detail["data"]["try"] == {"options": options}

    after = client.get("/api/stats?inspection=magnet_check&window_s=3600").json()
    assert after["inspections"][0]["count"] == before["inspections"][0]["count"]
    assert after["inspections"][0]["pass"] == before["inspections"][0]["pass"]
    metrics_after = client.get("/metrics").body.decode()
    for verdict in ("pass", "fail"):
        assert _metric(metrics_after, "magnet_check", verdict) == _metric(
            metrics_before, "magnet_check", verdict
        )

    # The CLI marks it too: a "try" column, and "try": true in its JSON lines.
    assert server.runtime is not None
    db = server.runtime.config.results.path
    assert db is not None
    out = io.StringIO()
    status = results_command(
        db,
        since=None,
        inspection="magnet_check",
        json_out=False,
        limit=1,
        failed_only=False,
        console=Console(file=out, width=200),
    )
    assert status == 0
    row_line = next(line for line in out.getvalue().splitlines() if "magnet_check" in line)
    assert " try " in row_line, out.getvalue()
