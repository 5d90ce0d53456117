"""2f. MQTT: results published to a broker, beside the binary protocol's answers.

One ``vision-server serve`` process (its own, with this section's configuration: a presence
check on a 64x48 image sent with each request, the SQLite result log on, ``mqtt:`` enabled)
and a private Debian ``mosquitto`` on loopback (its own configuration, persistence off). In one
run:

- **live**: INSPECTs over the binary protocol, 8 in flight on one connection, while an aiomqtt
  subscriber (QoS 1) receives the published results: the rate of RESULTs the client got and of
  result messages the subscriber got over the same run, and each result's delay from its
  RESULT's arrival at the client to its message's arrival at the subscriber (matched by the
  result log's id both carry);
- **backlog**: the broker stopped, results answered (and spooled), the broker started again:
  how fast the server empties its spool, from the broker's restart until PONG's health says no
  result waits (PUBACKed results per second, the reconnect included).
"""

from __future__ import annotations

import asyncio
import json
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from protocol import Ping, Pong

from .busy import make_client
from .common import ROOT, RunConfig, Section, Skip, Stats, Table, fmt
from .env import Env
from .plots import cdf, log_scale_if_positive, pyplot, save

NAME = "mqtt"
TITLE = "2f. MQTT: publish rate beside the binary protocol's"
IN_FLIGHT = 8
IMAGE = np.full((48, 64), 200, np.uint8)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _mosquitto() -> str:
    """The broker's program, installed by scripts/mosquitto_setup.sh where it can (Skip)."""
    done = subprocess.run(
        ["bash", str(ROOT / "scripts" / "mosquitto_setup.sh")],
        capture_output=True, text=True, timeout=900, check=False,
    )  # fmt: skip
    if done.returncode != 0:
        raise Skip(done.stderr.strip() or "scripts/mosquitto_setup.sh failed")
    found = dict(part.split("=", 1) for part in done.stdout.split() if "=" in part)
    return found["mosquitto"]


class _Broker:
    """A private mosquitto on ``port``; start() waits until it accepts connections."""

    def __init__(self, program: str, workdir: Path) -> None:
        self.program = program
        self.port = _free_port()
        self.config = workdir / "mosquitto.conf"
        self.config.write_text(
            f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
            + ("user root\n" if _root() else "")
        )
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [self.program, "-c", str(self.config)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.5).close()
                return
            except OSError:
                time.sleep(0.02)
        raise Skip("mosquitto did not listen within 15 s")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=15)
        self.proc = None


def _root() -> bool:
    import os

    return os.geteuid() == 0


def write_config(workdir: Path, broker_port: int) -> Path:
    doc: dict[str, Any] = {
        "server": {"port": 0, "name": "bench-cell"},
        "results": {"path": "results.sqlite3", "store_images": "none"},
        "cameras": {"tool": {"source": "request"}},
        "inspections": [
            {
                "name": "bright",
                "type": "presence",
                "camera": "tool",
                "measure": "mean_intensity",
                "min": 100,
            }
        ],
        "mqtt": {
            "enabled": True,
            "port": broker_port,
            "reconnect_min_s": 0.05,
            "reconnect_max_s": 0.2,
        },
    }
    path = workdir / "mqtt-cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


async def _live(port: int, broker_port: int, count: int) -> tuple[float, float, list[float]]:
    """(RESULTs per second, result messages per second, delays ms) of ``count`` INSPECTs."""
    import aiomqtt

    answered: dict[int, float] = {}
    arrived: dict[int, float] = {}
    done = asyncio.Event()
    async with aiomqtt.Client("127.0.0.1", broker_port, identifier="bench-sub") as sub:
        await sub.subscribe("cellvision/bench-cell/results/+", qos=1)

        async def receive() -> None:
            async for message in sub.messages:
                payload = message.payload
                assert isinstance(payload, bytes)
                arrived[int(json.loads(payload)["result_id"])] = time.perf_counter()
                if len(arrived) >= count:
                    done.set()

        receiver = asyncio.create_task(receive())
        client = make_client(port, busy_timeout_s=60.0)
        await client.connect()
        gate = asyncio.Semaphore(IN_FLIGHT)

        async def one() -> None:
            async with gate:
                result = await client.inspect("bright", IMAGE)
                answered[int(result.result_id)] = time.perf_counter()

        try:
            t0 = time.perf_counter()
            await asyncio.gather(*(one() for _ in range(count)))
            async with asyncio.timeout(120):
                await done.wait()
        finally:
            receiver.cancel()
            await client.close()
    delays = [(arrived[rid] - answered[rid]) * 1000.0 for rid in answered if rid in arrived]
    return (
        count / (max(answered.values()) - t0),
        count / (max(arrived.values()) - t0),
        delays,
    )


async def _spooled(port: int) -> int:
    client = make_client(port, busy_timeout_s=60.0)
    await client.connect()
    try:
        answer = await client.request(lambda rid: Ping(rid, ""))
        assert isinstance(answer, Pong)
        assert answer.health is not None
        return int(answer.health["mqtt"]["spooled"])
    finally:
        await client.close()


async def _answer(port: int, count: int) -> None:
    client = make_client(port, busy_timeout_s=60.0)
    await client.connect()
    gate = asyncio.Semaphore(IN_FLIGHT)

    async def one() -> None:
        async with gate:
            await client.inspect("bright", IMAGE)

    try:
        await asyncio.gather(*(one() for _ in range(count)))
    finally:
        await client.close()


async def _drained(port: int) -> float:
    """Seconds until PONG's health says the spool is empty (polled every 10 ms)."""
    t0 = time.perf_counter()
    async with asyncio.timeout(300):
        # Polling: the count is in another process, over PING.
        while await _spooled(port):  # noqa: ASYNC110
            await asyncio.sleep(0.01)
    return time.perf_counter() - t0


def run(cfg: RunConfig, env: Env) -> Section:
    from robot_client.demo.cell import vision_server

    try:
        import aiomqtt  # noqa: F401
    except ImportError as exc:
        raise Skip("aiomqtt is not installed: pip install 'cellvision[mqtt]'") from exc
    program = _mosquitto()
    live_n = cfg.n(3000, 40)
    backlog_n = cfg.n(3000, 40)
    section = Section(NAME, TITLE, intro=(__doc__ or "").split("\n\n", 1)[1].strip())
    workdir = Path(tempfile.mkdtemp(prefix="mqtt-", dir=cfg.workdir))
    broker = _Broker(program, workdir)
    broker.start()
    try:
        config = write_config(workdir, broker.port)
        with vision_server(config, workdir / "server-mqtt.log") as server:
            asyncio.run(_live(server.port, broker.port, cfg.n(100, 5)))  # warm-up
            results_s, messages_s, delays = asyncio.run(_live(server.port, broker.port, live_n))
            broker.stop()
            asyncio.run(_answer(server.port, backlog_n))
            waiting = asyncio.run(_spooled(server.port))
            broker.start()
            seconds = asyncio.run(_drained(server.port))
    finally:
        broker.stop()
        shutil.rmtree(workdir, ignore_errors=True)
    delay = Stats.of(delays)
    table = Table(
        ["measure", "value"],
        caption=f"{live_n} INSPECTs, {IN_FLIGHT} in flight, 64x48 image, result log on; "
        f"a backlog of {waiting} results",
    )
    table.add("binary protocol: RESULTs per second", fmt(results_s, 0))
    table.add("MQTT: result messages per second at a QoS 1 subscriber", fmt(messages_s, 0))
    table.add("RESULT to MQTT message, p50 ms", fmt(delay.p50))
    table.add("RESULT to MQTT message, p99 ms", fmt(delay.p99))
    table.add("spool emptied after the broker's restart, results per second",
              fmt(waiting / seconds, 0))  # fmt: skip
    section.tables.append(table)
    section.value("binary_results_per_s", results_s)
    section.value("mqtt_messages_per_s", messages_s)
    section.value("result_to_message_p50_ms", delay.p50)
    section.value("result_to_message_p99_ms", delay.p99)
    section.value("backlog_per_s", waiting / seconds)

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(5.5, 3.4))
        cdf(ax, delays, f"{live_n} results, {IN_FLIGHT} INSPECTs in flight")
        log_scale_if_positive(ax, "x")
        ax.set_xlabel("RESULT at the client to its MQTT message at the subscriber [ms]")
        ax.set_ylabel("fraction of results")
        ax.legend(loc="lower right", fontsize=8)
        return [save(fig, directory / "mqtt.png")]

    section.plot = plot
    section.notes.append(
        "Every result is written to the spool (SQLite, WAL) before its RESULT is sent and "
        "deleted at its PUBACK (docs/mqtt.md), so MQTT keeps pace with the answers only as "
        "long as the broker's PUBACKs do; the backlog's rate is that of a spool being emptied "
        "with the default 64 publishes in flight."
    )
    return section
