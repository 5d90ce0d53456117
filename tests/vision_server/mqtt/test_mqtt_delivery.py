"""Results to a real broker (Debian's mosquitto, tests/helpers/mosquitto.py): every
acknowledged RESULT arrives at a QoS 1 subscriber, schema-valid, through broker restarts and a
server restart with the broker down. Counted by the result log's ids the RESULTs carry."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiohttp
from loopback import run, wait_until
from mosquitto import Broker, Subscriber
from mqtt_cell import RESULTS, STATE, inspect, serving, valid_results, write_cell

from protocol import schema
from robot_client import VisionClient


def test_every_inspection_arrives_schema_valid_with_its_verdict(
    tmp_path: Path, broker: Broker
) -> None:
    path = write_cell(tmp_path, broker.port, "console: {enabled: true, port: 0}\n")
    count = 20

    async def body() -> None:
        async with Subscriber(broker.port, (RESULTS, STATE)) as subscriber:
            async with serving(path) as app:
                assert app.mqtt is not None
                async with VisionClient("127.0.0.1", app.port, request_timeout_s=10.0) as client:
                    answers = [await inspect(client, i % 3 != 0) for i in range(count)]
                await subscriber.wait_for(
                    lambda s: len(s.payloads("/results/bright")) >= count, "every result"
                )
                mqtt = app.mqtt
                await wait_until(lambda: mqtt.health()["spooled"] == 0, "every PUBACK")
                health = app.health()
                assert health["mqtt"]["connected"] is True
                assert health["mqtt"]["published"] == count
                assert health["ok"] is True
                assert app.http is not None
                async with (
                    aiohttp.ClientSession() as http,
                    http.get(f"{app.http.url}metrics") as reply,
                    http.get(f"{app.http.url}api/server") as server,
                ):
                    metrics = await reply.text()
                    checks = (await server.json())["health"]["checks"]
                assert {"name": "MQTT", "ok": True, "message": ""} in checks
                assert "cellvision_mqtt_connected 1.0" in metrics
                assert f"cellvision_mqtt_published_total {count}.0" in metrics
                assert "cellvision_mqtt_spooled 0.0" in metrics
                assert "cellvision_mqtt_dropped_total 0.0" in metrics
            got = valid_results(subscriber.payloads("/results/bright"))
            assert {rid: p["passed"] for rid, p in got.items()} == dict(answers)
            payloads = subscriber.payloads("/results/bright")
            assert [p["seq"] for p in payloads] == sorted(p["seq"] for p in payloads)
            assert len({p["uid"] for p in payloads}) == count
            first = payloads[0]
            assert (first["cell"], first["server"], first["inspection"]) == (
                "line-7",
                "line-7",
                "bright",
            )
            assert first["camera"] == "tool"
            assert "mean_intensity" in json.dumps(first["data"]) or first["data"]
            # The state topic: online while it ran, offline (stopped) once it stopped.
            await subscriber.wait_for(
                lambda s: (
                    s.payloads("/state")[-1:] and s.payloads("/state")[-1]["state"] == "offline"
                ),
                "the offline state at the stop",
            )
            states = subscriber.payloads("/state")
            for state in states:
                schema.validate_mqtt("state", state)
            assert [s["reason"] for s in states][-2:] == ["connected", "stopped"]

    run(body(), timeout_s=60)


def test_a_broker_restarted_mid_run_loses_no_acknowledged_result(
    tmp_path: Path, broker: Broker
) -> None:
    """INSPECTs go on, one after another, while the broker is stopped and started twice:
    every acknowledged RESULT's result arrives at the subscriber (counted by result id)."""
    path = write_cell(tmp_path, broker.port)
    answers: dict[int, bool] = {}

    async def body() -> None:
        async with Subscriber(broker.port, (RESULTS,)) as subscriber:
            async with (
                serving(path) as app,
                VisionClient("127.0.0.1", app.port, request_timeout_s=10.0) as client,
            ):
                mqtt = app.mqtt
                assert mqtt is not None
                feeding = True

                async def feed() -> None:
                    while feeding:
                        result_id, passed = await inspect(client, len(answers) % 3 != 0)
                        answers[result_id] = passed
                        await asyncio.sleep(0.002)

                async def ten_more(what: str) -> None:
                    mark = len(answers)
                    await wait_until(lambda: len(answers) >= mark + 10, what)

                feeder = asyncio.create_task(feed())
                for _ in range(2):
                    await ten_more("answers, the broker up")
                    await asyncio.to_thread(broker.stop)
                    await ten_more("answers, the broker away")
                    assert mqtt.health()["spooled"] >= 10
                    await asyncio.to_thread(broker.start)
                await ten_more("answers after the restarts")
                feeding = False
                await feeder
                await subscriber.wait_for(
                    lambda s: set(answers) <= {p["result_id"] for p in s.payloads()},
                    "every acknowledged result after the restarts",
                    timeout_s=30.0,
                )
                await wait_until(lambda: mqtt.health()["spooled"] == 0, "the spool emptied")
                assert mqtt.health()["connects"] >= 3
            got = valid_results(subscriber.payloads())
            assert len(answers) >= 50
            assert {rid: got[rid]["passed"] for rid in answers} == answers

    run(body(), timeout_s=90)


def test_results_spooled_while_broker_and_server_were_down_are_sent_later(
    tmp_path: Path, broker: Broker
) -> None:
    path = write_cell(tmp_path, broker.port)

    async def body() -> None:
        broker_stopped = asyncio.to_thread(broker.stop)
        await broker_stopped
        async with (
            serving(path) as app,
            VisionClient("127.0.0.1", app.port, request_timeout_s=10.0) as client,
        ):
            answers = dict([await inspect(client, i % 4 != 0) for i in range(12)])
            assert app.mqtt is not None
            assert app.mqtt.health()["spooled"] == 12
        assert (tmp_path / "mqtt-spool.sqlite").is_file()  # beside cell.yaml
        await asyncio.to_thread(broker.start)
        async with Subscriber(broker.port, (RESULTS,)) as subscriber, serving(path) as app:
            await subscriber.wait_for(
                lambda s: set(answers) <= {p["result_id"] for p in s.payloads()},
                "the results spooled before the restart",
            )
        got = valid_results(subscriber.payloads())
        assert {rid: got[rid]["passed"] for rid in answers} == answers
        seqs = sorted({got[rid]["seq"] for rid in answers})
        assert seqs == list(range(seqs[0], seqs[0] + 12))

    run(body(), timeout_s=60)
