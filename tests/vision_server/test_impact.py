"""Impact before save: the replay engine, ``POST /api/inspections/{name}/impact`` and
``vision-server replay`` on one real result log.

The log is made by a real server run (tests/helpers/impact_log.py): designed QC images sent to
``magnet_check`` through the protocol, stored by the server (``store_images: all``), half of
them under an earlier version of the file, with a console try among them. Every expected flip is
computed here from the images' design, not by the server; the API and the CLI must both give
exactly those flips, and the same answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from console_server import Browserless, RunningConsole, console_server
from impact_log import (
    BASE_MIN,
    BASE_THRESHOLD,
    Row,
    changed_config,
    expected_pass,
    fill_log,
    impact_server,
)

from vision_server.commands import main
from vision_server.service import Change, ChangeRefused, changed_inspection, replay
from vision_server.service.admission import try_key
from vision_server.service.replay import IMPACT_PEER

NEW_THRESHOLD = 120
NEW_MIN = 0.45


@pytest.fixture(scope="module")
def filled(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RunningConsole, list[Row]]]:
    folder = tmp_path_factory.mktemp("impact")
    with impact_server(folder) as server:
        yield server, fill_log(server)


def expected_flips(rows: list[Row], threshold: float, minimum: float) -> set[tuple[int, str, str]]:
    """(result id, stored, new) of every row whose verdict the change turns, from the design."""
    out = set()
    for row in rows:
        stored = expected_pass(row.design, BASE_THRESHOLD, BASE_MIN)
        new = expected_pass(row.design, threshold, minimum)
        if stored != new:
            out.add((row.result_id, _word(stored), _word(new)))
    return out


def _word(passed: bool) -> str:
    return "pass" if passed else "fail"


def flips_of(answer: dict[str, Any]) -> set[tuple[int, str, str]]:
    return {(f["result_id"], f["stored"], f["new"]) for f in answer["flipped"]}


def signed_in(server: RunningConsole) -> Browserless:
    client = Browserless(server.url)
    assert client.login().status == 200
    return client


def run_cli(*args: str) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["replay", *args])
    return code, out.getvalue()


# ----------------------------------------------------------------------------- the engine


def test_the_engine_flips_exactly_the_rows_the_design_predicts(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    server, rows = filled
    service = server.app.service
    log = service.results
    assert log is not None
    # The stored verdicts are the design's: the baseline the flips are measured against.
    for row in rows:
        stored = log.get(row.result_id)
        assert stored is not None
        assert stored.passed == expected_pass(row.design, BASE_THRESHOLD, BASE_MIN)
    before = log.count()
    catalog = service.catalog
    changed = changed_inspection(
        catalog, "magnet_check", Change(options={"threshold": NEW_THRESHOLD, "min": NEW_MIN})
    )

    async def run() -> Any:
        return await replay(
            service,
            log,
            changed,
            last=100,
            current_config_hash=catalog.config_hash,
            deadline=time.monotonic() + 120,
        )

    report = asyncio.run_coroutine_threadsafe(run(), server.loop).result(120)
    wanted = expected_flips(rows, NEW_THRESHOLD, NEW_MIN)
    assert wanted, "the design must flip some rows"
    assert {(f.result_id, _word(f.stored), _word(f.new)) for f in report.flipped} == wanted
    # Both directions, and rows of both configurations.
    assert {(s, n) for _, s, n in wanted} == {("pass", "fail"), ("fail", "pass")}
    assert report.considered == len(rows)  # the console try is left out
    assert report.with_image == len(rows)
    assert report.unchanged == len(rows) - len(wanted)
    assert report.failed == 0
    assert report.complete
    # Newest first, with each row's hash, marked when it is not the running configuration's.
    ids = [f.result_id for f in report.flipped]
    assert ids == sorted(ids, reverse=True)
    by_id = {row.result_id: row for row in rows}
    for flip in report.flipped:
        assert flip.stored_config_hash == by_id[flip.result_id].config_hash
        assert flip.current_config == (flip.stored_config_hash == catalog.config_hash)
        assert flip.overlay is not None
        assert flip.overlay.startswith("data:image/jpeg;base64,")
    assert {f.current_config for f in report.flipped} == {True, False}
    # A replay writes nothing to the result log.
    assert log.count() == before


def test_last_bounds_the_images_to_the_newest(filled: tuple[RunningConsole, list[Row]]) -> None:
    server, rows = filled
    client = signed_in(server)
    answer = client.post_json(
        "/api/inspections/magnet_check/impact",
        {"options": {"threshold": NEW_THRESHOLD, "min": NEW_MIN}, "last": 5},
    ).json()
    newest = sorted(rows, key=lambda r: r.result_id)[-5:]
    assert answer["with_image"] == 5
    assert flips_of(answer) == expected_flips(newest, NEW_THRESHOLD, NEW_MIN)


# ----------------------------------------------------------------------------- API and CLI


def test_the_api_and_the_cli_give_the_same_flips(
    filled: tuple[RunningConsole, list[Row]], tmp_path: Path
) -> None:
    server, rows = filled
    wanted = expected_flips(rows, NEW_THRESHOLD, NEW_MIN)
    client = signed_in(server)
    reply = client.post_json(
        "/api/inspections/magnet_check/impact",
        {"options": {"threshold": NEW_THRESHOLD, "min": NEW_MIN}, "last": 500},
    )
    assert reply.status == 200, reply.body
    api = reply.json()
    assert flips_of(api) == wanted
    assert api["considered"] == len(rows)
    assert api["with_image"] == len(rows)
    assert api["unchanged"] == len(rows) - len(wanted)
    assert api["pass_to_fail"] + api["fail_to_pass"] == len(wanted)
    assert api["store_images"] == "all"
    assert api["current_config_hash"] == server.app.service.catalog.config_hash

    changed = changed_config(server, tmp_path, NEW_THRESHOLD, NEW_MIN)
    code, out = run_cli("magnet_check", "--config", str(changed), "--last", "500", "--json")
    assert code == 1, out  # verdicts flip
    cli = json.loads(out)
    assert flips_of(cli) == wanted
    # The same answer: every flip's fields (the thumbnails are the same drawing's JPEGs).
    keys = ("result_id", "time", "stored", "new", "stored_config_hash", "current_config")
    assert [{k: f[k] for k in keys} for f in cli["flipped"]] == [
        {k: f[k] for k in keys} for f in api["flipped"]
    ]
    for key in ("considered", "with_image", "unchanged", "failed", "pass_to_fail"):
        assert cli[key] == api[key], key
    # With --running the file the server runs, the running configuration is known exactly.
    code, out = run_cli(
        "magnet_check", "--config", str(changed), "--json", "--running", str(server.config)
    )
    assert code == 1
    assert json.loads(out)["current_config_hash"] == api["current_config_hash"]


def test_a_whole_config_change_gives_the_same_flips_as_its_options(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    server, rows = filled
    client = signed_in(server)
    config = next(
        i["config"]
        for i in client.get("/api/inspections").json()["inspections"]
        if i["name"] == "magnet_check"
    )
    config = {**config, "threshold": NEW_THRESHOLD, "min": NEW_MIN}
    answer = client.post_json(
        "/api/inspections/magnet_check/impact", {"config": config, "last": 100}
    ).json()
    assert flips_of(answer) == expected_flips(rows, NEW_THRESHOLD, NEW_MIN)


def test_the_cli_prints_a_table_and_exits_0_when_nothing_flips(
    filled: tuple[RunningConsole, list[Row]], tmp_path: Path
) -> None:
    server, rows = filled
    same = changed_config(server, tmp_path, BASE_THRESHOLD, BASE_MIN)
    code, out = run_cli("magnet_check", "--config", str(same))
    assert code == 0, out
    assert f"{len(rows)} stored images replayed" in out
    assert "0 pass→fail, 0 fail→pass" in out
    changed = changed_config(server, tmp_path, NEW_THRESHOLD, NEW_MIN)
    code, out = run_cli("magnet_check", "--config", str(changed))
    assert code == 1
    for result_id, _, _ in expected_flips(rows, NEW_THRESHOLD, NEW_MIN):
        assert f"│ {result_id} " in out


def test_the_cli_names_what_is_wrong(
    filled: tuple[RunningConsole, list[Row]], tmp_path: Path
) -> None:
    server, _ = filled
    changed = changed_config(server, tmp_path, NEW_THRESHOLD, NEW_MIN)
    code, out = run_cli("nope", "--config", str(changed), "--json")
    assert code == 2
    assert json.loads(out)["error"]["code"] == "UNKNOWN_INSPECTION"
    bad = tmp_path / "bad.yaml"
    bad.write_text(changed.read_text().replace("threshold: 120", "threshold: 300"))
    code, out = run_cli("magnet_check", "--config", str(bad), "--json")
    assert code == 2
    error = json.loads(out)["error"]
    assert error["code"] == "CONFIG_INVALID"
    assert "threshold" in error["message"]
    code, out = run_cli("magnet_check", "--config", str(changed), "--last", "0", "--json")
    assert code == 2
    assert "--last" in json.loads(out)["error"]["message"]
    # A log with no stored image of the inspection: nothing to replay, said so.
    empty = tmp_path / "empty.yaml"
    empty.write_text(
        changed.read_text().replace(str(server.config.parent), str(tmp_path / "elsewhere"))
    )
    (tmp_path / "elsewhere").mkdir()
    from vision_server.results import ResultLog

    ResultLog(tmp_path / "elsewhere" / "results.sqlite3").close()
    code, out = run_cli("magnet_check", "--config", str(empty), "--json")
    assert code == 2
    error = json.loads(out)["error"]
    assert error["code"] == "NO_IMAGES"
    assert "store_images" in error["message"]


def test_the_api_refuses_bad_requests_naming_the_cause(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    server, _ = filled
    client = signed_in(server)
    path = "/api/inspections/magnet_check/impact"

    def refused(body: Any, status: int, code: str) -> dict[str, Any]:
        reply = client.post_json(path, body)
        assert reply.status == status, reply.body
        error = reply.json()["error"]
        assert error["code"] == code, error
        return dict(error)

    for last in (0, 1001, "5", True, 2.5):
        assert "last" in refused({"options": {}, "last": last}, 400, "BAD_REQUEST")["message"]
    refused({"last": 5}, 400, "BAD_REQUEST")
    refused({"options": {}, "config": {}}, 400, "BAD_REQUEST")
    refused({"options": [1]}, 400, "BAD_REQUEST")
    refused({"options": {}, "extra": 1}, 400, "BAD_REQUEST")
    error = refused({"options": {"threshold": 300}}, 400, "INVALID_ARGUMENT")
    assert error["key"] == "threshold"
    error = refused({"options": {"camera": "tool"}}, 400, "INVALID_ARGUMENT")
    assert "camera" in error["message"]
    error = refused({"config": {"name": "magnet_check", "type": "presence"}}, 400, "CONFIG_INVALID")
    assert error["key"] == "camera"
    config = {"name": "magnet_check", "type": "presence", "camera": "qc"}
    error = refused({"config": config}, 400, "CONFIG_INVALID")
    assert "missing required key 'measure'" in error["message"]
    config.update(measure="dark_fraction", roi=[486, 236, 50, 60], threshold=90, min="x")
    error = refused({"config": config}, 400, "CONFIG_INVALID")
    assert error["key"] == "min", error
    # Past the image the running (simulated) camera declares, 1024x768: refused as a save is.
    config.update(min=0.25, roi=[1000, 700, 100, 100])
    error = refused({"config": config}, 400, "CONFIG_INVALID")
    assert error["key"].startswith("roi"), error
    assert "1024" in error["message"], error
    reply = client.request("POST", path, b"not json", {"Content-Type": "application/json"})
    assert reply.status == 400
    assert reply.json()["error"]["code"] == "BAD_REQUEST"
    reply = client.request(
        "POST", path, b"{" + b" " * (70 * 1024) + b"}", {"Content-Type": "application/json"}
    )
    assert reply.status == 413
    reply = client.post_json("/api/inspections/nope/impact", {"options": {}})
    assert reply.status == 404
    assert reply.json()["error"]["code"] == "UNKNOWN_INSPECTION"


def test_changed_inspection_refuses_a_config_of_another_name(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    server, _ = filled
    with pytest.raises(ChangeRefused) as caught:
        changed_inspection(
            server.app.service.catalog,
            "magnet_check",
            Change(config={"name": "other", "type": "presence", "camera": "qc"}),
        )
    assert caught.value.code == "CONFIG_INVALID"
    assert caught.value.key == "name"


# ----------------------------------------------------------------------------- roles, no images


def test_the_preview_needs_the_integrators_role_and_the_consoles_header(tmp_path: Path) -> None:
    with console_server(tmp_path, operator_token="operator-token-0123456789") as server:
        path = "/api/inspections/magnet_check/impact"
        anonymous = Browserless(server.url)
        assert anonymous.post_json(path, {"options": {}}).status == 401
        operator = Browserless(server.url)
        assert operator.login("operator-token-0123456789").status == 200
        reply = operator.post_json(path, {"options": {}})
        assert reply.status == 403
        assert reply.json()["error"]["code"] == "FORBIDDEN"
        admin = signed_in(server)
        # Without the page's header another site's form could post it (docs/console.md).
        reply = admin.request(
            "POST",
            path,
            json.dumps({"options": {}}).encode(),
            {"Content-Type": "text/plain", "X-Cellvision": ""},
        )
        assert reply.status == 403
        assert reply.json()["error"]["code"] == "CROSS_SITE"
        # The default store_images (failures) and no failure yet: the answer says it.
        answer = admin.post_json(path, {"options": {"threshold": 100}}).json()
        assert answer["with_image"] == 0
        assert answer["flipped"] == []
        assert answer["store_images"] == "failures"


# ----------------------------------------------------------------------------- bounds


def test_a_passed_deadline_stops_the_run_and_says_so(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    server, _ = filled
    service = server.app.service
    assert service.results is not None
    inspection = service.catalog.inspection("magnet_check")

    async def run() -> Any:
        return await replay(
            service,
            service.results,
            inspection,
            last=10,
            current_config_hash="",
            deadline=time.monotonic() - 1,
        )

    report = asyncio.run_coroutine_threadsafe(run(), server.loop).result(60)
    assert not report.complete
    assert report.stopped_by == "deadline"
    assert report.with_image == 0
    assert report.flipped == []


def test_a_cancelled_run_stops_and_frees_the_try_lane(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    server, rows = filled
    service = server.app.service
    assert service.results is not None
    inspection = service.catalog.inspection("magnet_check")
    seen: list[int] = []

    async def start() -> asyncio.Task[Any]:
        # Cancelled as soon as its first image has been run, as a browser that goes away.
        def observe(record: Any) -> None:
            if record.request.peer == IMPACT_PEER:
                seen.append(record.request.request_id)
                if len(seen) == 1:
                    task.cancel()

        unsubscribe = service.subscribe(observe)
        task = asyncio.create_task(
            replay(
                service,
                service.results,
                inspection,
                last=100,
                current_config_hash="",
                deadline=time.monotonic() + 60,
            )
        )
        task.add_done_callback(lambda _: unsubscribe())
        return task

    task = asyncio.run_coroutine_threadsafe(start(), server.loop).result(10)

    async def outcome() -> str:
        try:
            await task
        except asyncio.CancelledError:
            return "cancelled"
        return "finished"

    assert asyncio.run_coroutine_threadsafe(outcome(), server.loop).result(60) == "cancelled"
    assert len(seen) < len(rows)
    assert service.pool.tries.admitted == 0


def test_a_browser_that_goes_away_stops_the_preview(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    server, rows = filled
    service = server.app.service
    seen: list[int] = []
    cut = threading.Event()

    def observe(record: Any) -> None:
        if record.request.peer == IMPACT_PEER:
            seen.append(record.request.request_id)
            if len(seen) == 1:
                cut.set()

    unsubscribe = server.call(lambda: service.subscribe(observe))
    try:
        client = signed_in(server)
        cookie = "; ".join(f"{c.name}={c.value}" for c in client.jar)
        body = json.dumps({"options": {"threshold": 120}, "last": 100}).encode()
        host, port = server.app.http.address if server.app.http else ("", 0)
        with socket.create_connection((host, port)) as raw:
            raw.sendall(
                (
                    f"POST /api/inspections/magnet_check/impact HTTP/1.1\r\nHost: {host}:{port}\r\n"
                    f"Content-Type: application/json\r\nCookie: {cookie}\r\n"
                    f"Content-Length: {len(body)}\r\n\r\n"
                ).encode()
                + body
            )
            assert cut.wait(60), "the preview never ran an image"
        # The connection is closed after its first image: the run stops, the lane is freed.
        deadline = time.monotonic() + 60
        while service.pool.tries.admitted and time.monotonic() < deadline:
            time.sleep(0.05)
        stopped_at = len(seen)
        time.sleep(0.5)
        assert len(seen) == stopped_at
        assert stopped_at < len(rows)
    finally:
        server.call(unsubscribe)


def test_an_image_that_cannot_be_read_is_listed_and_the_rest_replayed(
    filled: tuple[RunningConsole, list[Row]], tmp_path: Path
) -> None:
    server, rows = filled
    log = server.app.service.results
    assert log is not None
    broken = log.get(rows[-1].result_id)
    assert broken is not None
    assert broken.image_path is not None
    kept = broken.image_path.read_bytes()
    broken.image_path.write_bytes(b"not a png")
    try:
        answer = (
            signed_in(server)
            .post_json(
                "/api/inspections/magnet_check/impact",
                {"options": {"threshold": NEW_THRESHOLD, "min": NEW_MIN}, "last": 100},
            )
            .json()
        )
        assert answer["failed"] == 1
        assert answer["errors"][0]["result_id"] == broken.id
        assert answer["errors"][0]["code"] == "BAD_IMAGE"
        assert answer["with_image"] == len(rows)
        assert flips_of(answer) == expected_flips(rows[:-1], NEW_THRESHOLD, NEW_MIN)
        changed = changed_config(server, tmp_path, NEW_THRESHOLD, NEW_MIN)
        code, out = run_cli("magnet_check", "--config", str(changed), "--json")
        assert code == 4
        assert json.loads(out)["errors"] == answer["errors"]
    finally:
        broken.image_path.write_bytes(kept)


def test_the_installed_command_runs_as_a_user_runs_it(
    filled: tuple[RunningConsole, list[Row]], tmp_path: Path
) -> None:
    """``python -m vision_server replay`` in a process of its own (the program path: its
    arguments, the decoder limits, stdout) gives the flips the design predicts."""
    server, rows = filled
    changed = changed_config(server, tmp_path, NEW_THRESHOLD, NEW_MIN)
    done = subprocess.run(
        [sys.executable, "-m", "vision_server", "replay", "magnet_check", "--config", str(changed)]
        + ["--last", "1000", "--json"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 1, done.stderr
    assert flips_of(json.loads(done.stdout)) == expected_flips(rows, NEW_THRESHOLD, NEW_MIN)
    done = subprocess.run(
        [sys.executable, "-m", "vision_server", "replay", "magnet_check", "--config", str(changed)]
        + ["--last", "1001"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 2
    assert "--last must be in 1..1000" in done.stderr


def test_previews_wait_for_the_try_lane_and_a_third_at_once_is_busy(
    filled: tuple[RunningConsole, list[Row]],
) -> None:
    """With the try lane taken (a person's tries), two previews wait for it, a third is
    refused BUSY at once; when the lane frees, both waiting previews finish whole."""
    server, rows = filled
    service = server.app.service
    lane = service.pool.tries
    held = server.call(
        lambda: [service.pool.try_reserve(try_key("magnet_check")) for _ in range(lane.capacity)]
    )
    assert all(held)
    body = {"options": {"threshold": NEW_THRESHOLD, "min": NEW_MIN}, "last": 100}
    path = "/api/inspections/magnet_check/impact"
    try:
        with ThreadPoolExecutor(max_workers=2) as pool:
            waiting = [pool.submit(signed_in(server).post_json, path, body) for _ in range(2)]
            deadline = time.monotonic() + 60
            while len(lane.waiters) < 2 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert len(lane.waiters) == 2
            third = signed_in(server).post_json(path, body)
            assert third.status == 503
            assert third.json()["error"]["code"] == "BUSY"
            assert third.headers["Retry-After"]
            server.call(lambda: [service.pool.release(slot) for slot in held])
            held = []
            for future in waiting:
                answer = future.result(120)
                assert answer.status == 200, answer.body
                result = answer.json()
                assert result["complete"]
                assert flips_of(result) == expected_flips(rows, NEW_THRESHOLD, NEW_MIN)
    finally:
        server.call(lambda: [service.pool.release(slot) for slot in held])
