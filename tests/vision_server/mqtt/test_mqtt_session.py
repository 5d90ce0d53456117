"""The MQTT session against a real mosquitto: the last will when the server process dies,
TLS with a username and password, a refused password (logged, inspections still served),
what is not published (console tries, impact replays), and the spool's bound."""

from __future__ import annotations

import asyncio
import logging
import re
import signal
import ssl
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from loopback import run, wait_until
from mosquitto import Broker, Programs, Subscriber, make_tls
from mqtt_cell import PASSING, RESULTS, STATE, inspect, serving, valid_results, write_cell

from protocol import schema
from robot_client import VisionClient
from vision_server.service import Images, InspectRequest


def test_the_state_turns_offline_by_the_last_will_when_the_server_is_killed(
    tmp_path: Path, broker: Broker
) -> None:
    path = write_cell(tmp_path, broker.port)

    async def body() -> None:
        async with Subscriber(broker.port, (STATE,)) as subscriber:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "vision_server", "serve", "--config", str(path),
                cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            try:
                assert proc.stdout is not None
                lines = [(await proc.stdout.readline()).decode() for _ in range(2)]
                assert lines[1].strip() == f"vision-server: MQTT to 127.0.0.1:{broker.port}"
                port = int(re.findall(r":(\d+)", lines[0])[-1])
                await subscriber.wait_for(
                    lambda s: [p["state"] for p in s.payloads()][-1:] == ["online"], "online"
                )
                async with VisionClient("127.0.0.1", port, request_timeout_s=10.0) as client:
                    await inspect(client, True)
                proc.send_signal(signal.SIGKILL)
                await proc.wait()
            finally:
                if proc.returncode is None:
                    proc.kill()
                    await proc.wait()
            await subscriber.wait_for(
                lambda s: [p["state"] for p in s.payloads()][-1:] == ["offline"],
                "the last will",
            )
        will = subscriber.payloads()[-1]
        schema.validate_mqtt("state", will)
        assert will["reason"] == "connection_lost"
        assert will["cell"] == "line-7"
        assert subscriber.messages[-1][0] == STATE

    run(body(), timeout_s=60)


@pytest.fixture
def secured(mosquitto_programs: Programs, tmp_path: Path) -> Iterator[tuple[Broker, Path]]:
    """A broker that asks for a username and password, with a TLS listener; its CA file."""
    tls = make_tls(tmp_path)
    broker = Broker(mosquitto_programs, users={"cell7": "s3cret-pw"}, anonymous=False, tls=tls)
    try:
        broker.start()
        yield broker, tls.ca
    finally:
        broker.close()


def test_tls_with_a_username_and_a_password_file(
    tmp_path: Path, secured: tuple[Broker, Path]
) -> None:
    broker, ca = secured
    assert broker.tls_port is not None
    cell_dir = tmp_path / "cell"
    cell_dir.mkdir()
    (cell_dir / "mqtt-password").write_text("s3cret-pw\n")
    extra = f"  tls: {{ca: {ca}}}\n  username: cell7\n  password_file: mqtt-password\n"
    path = write_cell(cell_dir, broker.tls_port, extra)
    trusted = ssl.create_default_context(cafile=str(ca))

    async def body() -> None:
        async with (
            Subscriber(
                broker.tls_port or 0, (RESULTS,), "cell7", "s3cret-pw", trusted
            ) as subscriber,
            serving(path) as app,
            VisionClient("127.0.0.1", app.port, request_timeout_s=10.0) as client,
        ):
            answers = dict([await inspect(client, i % 2 == 1) for i in range(6)])
            await subscriber.wait_for(
                lambda s: set(answers) <= {p["result_id"] for p in s.payloads()}, "results"
            )
        got = valid_results(subscriber.payloads())
        assert {rid: got[rid]["passed"] for rid in answers} == answers

    run(body(), timeout_s=60)


def test_a_wrong_password_is_logged_and_inspections_are_still_served(
    tmp_path: Path,
    secured: tuple[Broker, Path],
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    broker, _ = secured
    monkeypatch.setenv("CELLVISION_TEST_MQTT_PW", "not-the-password")
    extra = "  username: cell7\n  password_env: CELLVISION_TEST_MQTT_PW\n"
    path = write_cell(tmp_path, broker.port, extra)
    caplog.set_level(logging.WARNING, logger="vision_server.mqtt")

    async def body() -> None:
        async with (
            serving(path) as app,
            VisionClient("127.0.0.1", app.port, request_timeout_s=10.0) as client,
        ):
            mqtt = app.mqtt
            assert mqtt is not None
            await wait_until(lambda: mqtt.last_error is not None, "the refusal", 20.0)
            answers = [await inspect(client, True) for _ in range(3)]
            assert [passed for _, passed in answers] == [True] * 3
            health = mqtt.health()
            assert health["connected"] is False
            assert health["spooled"] == 3
            assert "refused the connection" in health["last_error"]

    run(body(), timeout_s=60)
    refusals = [r for r in caplog.records if "refused the connection" in r.getMessage()]
    assert refusals
    assert refusals[0].levelno == logging.ERROR
    assert "check mqtt.username, the password" in refusals[0].getMessage()
    assert "not-the-password" not in caplog.text


def test_console_tries_and_unrecorded_runs_are_not_published(
    tmp_path: Path, broker: Broker
) -> None:
    path = write_cell(tmp_path, broker.port)

    async def body() -> None:
        async with Subscriber(broker.port, (RESULTS,)) as subscriber, serving(path) as app:
            service = app.service
            await service.inspect(
                InspectRequest("bright", Images(PASSING), request_class="try", peer="try:x")
            )
            await service.inspect(InspectRequest("bright", Images(PASSING), record=False))
            reply = await service.inspect(InspectRequest("bright", Images(PASSING), peer="plc"))
            await subscriber.wait_for(lambda s: len(s.payloads()) >= 1, "the production run")
            mqtt = app.mqtt
            assert mqtt is not None
            await wait_until(lambda: mqtt.health()["spooled"] == 0, "acknowledged")
        payloads = subscriber.payloads()
        assert [(p["result_id"], p["peer"]) for p in payloads] == [(reply.result_id, "plc")]

    run(body(), timeout_s=60)


def test_past_its_bound_the_spool_drops_the_oldest_and_health_says_so(
    tmp_path: Path, broker: Broker, caplog: pytest.LogCaptureFixture
) -> None:
    """About 3 payloads fit in 2 KB: the broker is away for 12 results."""
    path = write_cell(tmp_path, broker.port, "  spool_max_mb: 0.002\n")
    caplog.set_level(logging.ERROR, logger="vision_server.mqtt")

    async def body() -> None:
        # Subscribed first (a persistent session the broker keeps over its restart): the
        # server may publish before this client is back.
        async with Subscriber(broker.port, (RESULTS,)) as subscriber:
            await asyncio.to_thread(broker.stop)
            answers, kept = await spool_over_its_bound(subscriber)
        got = valid_results(subscriber.payloads())
        assert sorted(got) == answers[-kept:]  # the newest kept, the oldest dropped
        drops = [r for r in caplog.records if "is full" in r.getMessage()]
        assert drops  # said in the log (once per interval)
        assert len(drops) <= 2

    async def spool_over_its_bound(subscriber: Subscriber) -> tuple[list[int], int]:
        async with (
            serving(path) as app,
            VisionClient("127.0.0.1", app.port, request_timeout_s=10.0) as client,
        ):
            answers = [rid for rid, _ in [await inspect(client, True) for _ in range(12)]]
            mqtt = app.mqtt
            assert mqtt is not None
            health = app.health()
            assert health["ok"] is False
            assert health["mqtt"]["ok"] is False
            kept = health["mqtt"]["spooled"]
            assert 1 <= kept < 12
            assert health["mqtt"]["dropped"] == 12 - kept
            assert health["mqtt"]["spooled_bytes"] <= 0.002 * 2**20
            await asyncio.to_thread(broker.start)
            await subscriber.wait_for(lambda s: len(s.payloads()) >= kept, "the newest results")
            return answers, kept

    run(body(), timeout_s=60)


def test_a_broker_certificate_from_another_ca_is_refused_and_said(
    tmp_path: Path, secured: tuple[Broker, Path], caplog: pytest.LogCaptureFixture
) -> None:
    broker, _ = secured
    assert broker.tls_port is not None
    other = tmp_path / "other"
    other.mkdir()
    stranger = make_tls(other).ca
    extra = f"  tls: {{ca: {stranger}}}\n  username: cell7\n  password: s3cret-pw\n"
    path = write_cell(tmp_path / "cell", broker.tls_port, extra)
    caplog.set_level(logging.WARNING, logger="vision_server.mqtt")

    async def body() -> None:
        async with (
            serving(path) as app,
            VisionClient("127.0.0.1", app.port, request_timeout_s=10.0) as client,
        ):
            mqtt = app.mqtt
            assert mqtt is not None
            await wait_until(lambda: mqtt.last_error is not None, "the refusal", 20.0)
            assert (await inspect(client, True))[1] is True
            assert mqtt.health()["connected"] is False
            assert mqtt.health()["spooled"] == 1

    run(body(), timeout_s=60)
    refused = [r for r in caplog.records if "no TLS connection" in r.getMessage()]
    assert refused
    assert refused[0].levelno == logging.ERROR
    assert "certificate verify failed" in refused[0].getMessage()


def test_results_acknowledged_before_the_server_was_killed_are_sent_after_its_restart(
    tmp_path: Path, broker: Broker
) -> None:
    """The spool is written before each RESULT is sent: SIGKILL (no stop, no flush) loses
    none of the answered results."""
    path = write_cell(tmp_path, broker.port)

    async def body() -> None:
        await asyncio.to_thread(broker.stop)
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "vision_server", "serve", "--config", str(path),
            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            assert proc.stdout is not None
            port = int(re.findall(r":(\d+)", (await proc.stdout.readline()).decode())[-1])
            async with VisionClient("127.0.0.1", port, request_timeout_s=10.0) as client:
                answers = dict([await inspect(client, i % 2 == 0) for i in range(8)])
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        await asyncio.to_thread(broker.start)
        async with Subscriber(broker.port, (RESULTS,)) as subscriber, serving(path):
            await subscriber.wait_for(
                lambda s: set(answers) <= {p["result_id"] for p in s.payloads()},
                "the results answered before the kill",
            )
        got = valid_results(subscriber.payloads())
        assert {rid: got[rid]["passed"] for rid in answers} == answers

    run(body(), timeout_s=60)
