"""``GET /api/results.csv``: the result log as CSV through the console's front door, with the
Results page's filters, streamed page by page (vision_server/frontends/http_export.py), against
the real server with the example cell and its real SQLite log."""

from __future__ import annotations

import csv
import io
import json
import time
from collections.abc import Iterator

import pytest
from console_server import TOKEN, Browserless, RunningConsole, console_server

from vision_server.frontends import http_export
from vision_server.results import ResultEntry


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        log = running.app.service.results
        assert log is not None
        start = time.time() - 1000
        # 1203 rows: more than two of the export's pages, of two inspections, both verdicts,
        # and text a spreadsheet would take for a formula.
        for i in range(1203):
            log.record(
                ResultEntry(
                    time=start + i * 0.5,
                    inspection="magnet_check" if i % 3 else "cap_locate",
                    camera="qc",
                    passed=i % 4 != 0,
                    data={"value": i, "text": '=HYPERLINK("x")' if i == 7 else 'ok, "quoted"'},
                    duration_ms=1.5,
                    config_hash="abc",
                    request_id=i,
                    peer="-10.0.0.7:41000" if i == 9 else "10.0.0.7:41000",
                )
            )
        yield running


def _csv(client: Browserless, query: str = "") -> list[dict[str, str]]:
    reply = client.get("/api/results.csv" + query)
    assert reply.status == 200, reply.body[:300]
    assert reply.headers["Content-Type"].startswith("text/csv")
    assert "attachment" in reply.headers["Content-Disposition"]
    # Streamed before the middleware that adds them elsewhere: the security headers all the same.
    assert reply.headers["X-Content-Type-Options"] == "nosniff"
    assert "default-src 'self'" in reply.headers["Content-Security-Policy"]
    rows = list(csv.DictReader(io.StringIO(reply.body.decode("utf-8"))))
    return rows


@pytest.fixture
def client(server: RunningConsole) -> Browserless:
    c = Browserless(server.url)
    assert c.login().status == 200
    return c


def test_the_export_is_the_filtered_log_newest_first_across_pages(
    server: RunningConsole, client: Browserless
) -> None:
    log = server.app.service.results
    assert log is not None
    rows = _csv(client, "?inspection=magnet_check&verdict=fail&limit=100000")
    expected = log.query(inspection="magnet_check", passed=False, limit=100000)
    assert [int(r["id"]) for r in rows] == [e.id for e in expected]
    assert len(rows) > http_export.PAGE_ROWS / 4
    assert all(r["verdict"] == "fail" and r["inspection"] == "magnet_check" for r in rows)
    everything = _csv(client, "?limit=100000")
    assert len(everything) == log.count()
    ids = [int(r["id"]) for r in everything]
    assert ids == sorted(ids, reverse=True)
    assert list(everything[0].keys()) == list(http_export.COLUMNS)


def test_limit_cuts_the_export_and_the_default_is_bounded(client: Browserless) -> None:
    assert len(_csv(client, "?limit=501")) == 501
    assert len(_csv(client, "?limit=3")) == 3
    assert http_export.DEFAULT_ROWS <= http_export.MAX_ROWS


def test_values_round_trip_and_formulas_are_defused(client: Browserless) -> None:
    rows = {int(r["request_id"]): r for r in _csv(client, "?limit=100000") if r["request_id"]}
    seventh = json.loads(rows[7]["data"])
    assert seventh["text"] == '=HYPERLINK("x")'  # inside the JSON cell, not at its start
    assert json.loads(rows[8]["data"])["text"] == 'ok, "quoted"'
    assert rows[9]["peer"] == "'-10.0.0.7:41000"
    assert rows[8]["peer"] == "10.0.0.7:41000"


def test_bad_parameters_are_typed_json_errors(client: Browserless) -> None:
    for query, word in (
        ("?verdict=maybe", "verdict"),
        ("?limit=0", "limit"),
        ("?limit=x", "limit"),
        ("?since=nan", "since"),
        ("?since=yesterday", "since"),
    ):
        reply = client.get("/api/results.csv" + query)
        assert reply.status == 400, query
        error = reply.json()["error"]
        assert error["code"] == "BAD_REQUEST", (query, error)
        assert word in error["message"], (query, error)


def test_the_export_needs_a_session(server: RunningConsole) -> None:
    anonymous = Browserless(server.url)
    assert anonymous.get("/api/results.csv").status == 401
    signed_in = Browserless(server.url)
    assert signed_in.login(TOKEN).status == 200
    assert signed_in.get("/api/results.csv?limit=1").status == 200
