"""20. The plant: OPC UA trigger to result, and MQTT's publish rate, beside the binary protocol.

One ``vision-server serve`` process (its own, with this section's configuration) serves the
1024x768 server camera of section 2e (a folder camera replaying the tool camera's view of the
conveyor) with ``cap_locate`` (tens of ms) and ``brightness`` (well under a millisecond of
compute, so that a front-end's own cost shows), with the OPC UA front-end and, where Debian's
``mosquitto`` is installed, MQTT publishing to a private broker on loopback.

- **OPC UA**: asyncua's client in a SignAndEncrypt session (Basic256Sha256, a user and
  password), as an MES would run a job: ``StartSingleJob`` then the ``ResultReadyEvent`` of its
  subscription (publishing interval ``EVENT_INTERVAL_MS``), and ``StartSingleJob`` then
  ``GetResultById(JobId, Timeout)`` (which waits for the job: a whole job without a
  subscription). Alternated with the binary protocol's ``INSPECT`` of the same inspection (no
  image: the server's camera), request by request, so that all share the machine's load.
- **MQTT**: binary-protocol clients run ``brightness`` as fast as the server answers for a few
  seconds; the results the server answered per second and the result messages a subscriber
  received per second (QoS 1), and how long after its RESULT each message arrived.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml

from .busy import make_client
from .common import Goal, RunConfig, Section, Stats, Table, fmt, ratio
from .env import Env
from .line import _free_port
from .line import write_config as write_line_config
from .plots import cdf, log_scale_if_positive, pyplot, save

NAME = "plant"
TITLE = "20. The plant: OPC UA trigger to result and MQTT publish rate, beside the binary protocol"
INSPECTIONS = ("brightness", "cap_locate")
EVENT_INTERVAL_MS = 0
"""The subscription's publishing interval asked for (0: the server's fastest)."""
OPERATOR = ("operator", "bench-operator-token")
MV = "http://opcfoundation.org/UA/MachineVision"
CELL = "urn:cellvision:opcua"


def write_config(workdir: Path, opcua_port: int, mqtt_port: int | None) -> Path:
    """Section 2e's cell with OPC UA (and MQTT when a broker port is given) enabled."""
    path = write_line_config(workdir, _free_port())
    doc: dict[str, Any] = yaml.safe_load(path.read_text(encoding="utf-8"))
    doc["line"] = {"enabled": False}
    # The result log on: its row ids tie each MQTT message to the RESULT that answered it.
    doc["results"] = {"path": str(workdir / "plant-results.sqlite"), "store_images": "none"}
    doc["server"]["name"] = "bench-plant"
    doc["server"]["operator_token"] = OPERATOR[1]
    doc["opcua"] = {
        "enabled": True,
        "host": "127.0.0.1",
        "port": opcua_port,
        "pki": str(workdir / "plant-pki"),
        "trust_all_clients": True,
    }
    if mqtt_port is not None:
        doc["mqtt"] = {
            "enabled": True,
            "host": "127.0.0.1",
            "port": mqtt_port,
            "spool": str(workdir / "plant-mqtt-spool.sqlite"),
        }
    out = workdir / "plant-cell.yaml"
    out.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return out


# ---------------------------------------------------------------------------- OPC UA


class _Events:
    def __init__(self) -> None:
        self.queue: asyncio.Queue[Any] = asyncio.Queue()

    def event_notification(self, event: Any) -> None:
        self.queue.put_nowait(event)


async def _opcua_vs_binary(
    port: int, opcua_port: int, workdir: Path, name: str, repeat: int, warmup: int
) -> dict[str, list[float]]:
    """ms per trigger: binary INSPECT, OPC UA start → event, OPC UA start → GetResultById."""
    from asyncua import Client, ua
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key, cert = workdir / "plant-client-key.pem", workdir / "plant-client.der"
    uri = "urn:cellvision:bench:client"
    await setup_self_signed_certificate(
        key, cert, uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "bench"}
    )
    opc = Client(f"opc.tcp://127.0.0.1:{opcua_port}/cellvision", timeout=30)
    opc.application_uri = uri
    await opc.set_security(
        SecurityPolicyBasic256Sha256,
        str(cert),
        str(key),
        mode=ua.MessageSecurityMode.SignAndEncrypt,
    )
    opc.set_user(OPERATOR[0])
    opc.set_password(OPERATOR[1])
    binary_client = make_client(port, busy_timeout_s=60.0)
    await binary_client.connect()
    samples: dict[str, list[float]] = {"binary": [], "opcua_event": [], "opcua_by_id": []}
    async with opc:
        await opc.load_data_type_definitions()
        mv = await opc.get_namespace_index(MV)
        cell = await opc.get_namespace_index(CELL)
        system = await opc.nodes.objects.get_child(f"{cell}:VisionSystem")
        automatic = await system.get_child(
            [f"{mv}:VisionStateMachine", f"{mv}:AutomaticModeStateMachine"]
        )
        start = await automatic.get_child(f"{mv}:StartSingleJob")
        results = await system.get_child(f"{mv}:ResultManagement")
        by_id = await results.get_child(f"{mv}:GetResultById")
        events = _Events()
        subscription = await opc.create_subscription(EVENT_INTERVAL_MS, events)
        await subscription.subscribe_events(system, ua.NodeId(1024, mv))
        arguments = (
            ua.MeasIdDataType(Id=""),
            ua.PartIdDataType(Id=""),
            ua.RecipeIdExternalDataType(Id=name),
            ua.ProductIdDataType(Id=""),
            ua.Variant([], ua.VariantType.Variant),
        )
        try:
            for i in range(warmup + repeat):
                t0 = time.perf_counter_ns()
                answer = await binary_client.inspect(name)
                t1 = time.perf_counter_ns()
                if answer.inspection != name:
                    raise RuntimeError(f"INSPECT {name} answered {answer.inspection}")
                job, _error = await automatic.call_method(start, *arguments)
                event = await asyncio.wait_for(events.queue.get(), 30)
                t2 = time.perf_counter_ns()
                if event.JobId.Id != job.Id or event.ResultState != 1:
                    raise RuntimeError(f"job {job.Id}: event {event.JobId} {event.ResultState}")
                t3 = time.perf_counter_ns()
                job, _error = await automatic.call_method(start, *arguments)
                _handle, result, _error = await results.call_method(
                    by_id, ua.ResultIdDataType(Id=job.Id), ua.Variant(30_000, ua.VariantType.Int32)
                )
                t4 = time.perf_counter_ns()
                await events.queue.get()  # this job's event too: the next wait starts empty
                if result.ResultState != 1:
                    raise RuntimeError(f"job {job.Id}: {result.ResultState}")
                if i >= warmup:
                    samples["binary"].append((t1 - t0) / 1e6)
                    samples["opcua_event"].append((t2 - t1) / 1e6)
                    samples["opcua_by_id"].append((t4 - t3) / 1e6)
        finally:
            await binary_client.close()
    return samples


# ---------------------------------------------------------------------------- MQTT


@contextlib.contextmanager
def _mosquitto(port: int, workdir: Path) -> Iterator[subprocess.Popen[bytes]]:
    conf = workdir / "plant-mosquitto.conf"
    conf.write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n", encoding="utf-8"
    )
    process = subprocess.Popen(
        ["mosquitto", "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        _wait_port(port)
        yield process
    finally:
        process.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=10)
        if process.poll() is None:
            process.kill()


def _wait_port(port: int, timeout_s: float = 10.0) -> None:
    import socket

    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
            return
        time.sleep(0.05)
    raise RuntimeError(f"nothing listens on {port}")


async def _mqtt_rates(
    port: int, mqtt_port: int, seconds: float, clients: int
) -> tuple[float, float, list[float]]:
    """(results answered per s, messages received per s, ms from RESULT to arrival)."""
    import aiomqtt

    answered: dict[str, float] = {}
    arrived: dict[str, float] = {}
    stop = asyncio.Event()

    async def subscriber(ready: asyncio.Event) -> None:
        async with aiomqtt.Client("127.0.0.1", mqtt_port, identifier="bench-sub") as sub:
            await sub.subscribe("#", qos=1)
            ready.set()
            async for message in sub.messages:
                if "/results/" not in str(message.topic):
                    continue
                body = json.loads(bytes(message.payload))
                arrived.setdefault(str(body.get("result_id")), time.perf_counter())
                if stop.is_set() and len(arrived) >= len(answered):
                    return

    async def driver() -> None:
        client = make_client(port, busy_timeout_s=60.0)
        await client.connect()
        try:
            while not stop.is_set():
                answer = await client.inspect("brightness")
                answered[str(answer.result_id)] = time.perf_counter()
        finally:
            await client.close()

    ready = asyncio.Event()
    listening = asyncio.create_task(subscriber(ready))
    await asyncio.wait_for(ready.wait(), 10)
    t0 = time.perf_counter()
    drivers = [asyncio.create_task(driver()) for _ in range(clients)]
    await asyncio.sleep(seconds)
    stop.set()
    await asyncio.gather(*drivers)
    elapsed = time.perf_counter() - t0
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(listening, 30)
    last = max(arrived.values(), default=t0)
    delays = [(arrived[uid] - t) * 1000.0 for uid, t in answered.items() if uid in arrived]
    return len(answered) / elapsed, len(arrived) / max(last - t0, 1e-9), delays


# ---------------------------------------------------------------------------- the section


def run(cfg: RunConfig, env: Env) -> Section:
    from robot_client.demo.cell import vision_server

    repeat = cfg.n(200, 5)
    warmup = cfg.n(20, 2)
    section = Section(NAME, TITLE, intro=(__doc__ or "").split("\n\n", 1)[1].strip())
    opcua_port = _free_port()
    broker = shutil.which("mosquitto")
    mqtt_port = _free_port() if broker else None
    config = write_config(cfg.workdir, opcua_port, mqtt_port)
    table = Table(
        [
            "inspection",
            "binary INSPECT p50 ms",
            "OPC UA start → event p50 ms",
            "OPC UA start → GetResultById p50 ms",
            "event / binary p50",
            "by id / binary p50",
            "p99 ms (binary, event, by id)",
        ],
        caption=(
            f"{repeat} triggers each, alternated, one at a time; 1024x768 server camera; OPC UA "
            "over SignAndEncrypt (Basic256Sha256)"
        ),
    )
    samples: dict[str, dict[str, list[float]]] = {}
    with contextlib.ExitStack() as stack:
        if mqtt_port is not None:
            stack.enter_context(_mosquitto(mqtt_port, cfg.workdir))
        server = stack.enter_context(vision_server(config, cfg.workdir / "server-plant.log"))
        for name in INSPECTIONS:
            got = asyncio.run(
                _opcua_vs_binary(server.port, opcua_port, cfg.workdir, name, repeat, warmup)
            )
            samples[name] = got
            b, e, r = (Stats.of(got[k]) for k in ("binary", "opcua_event", "opcua_by_id"))
            table.add(
                name,
                fmt(b.p50),
                fmt(e.p50),
                fmt(r.p50),
                ratio(e.p50, b.p50, 2),
                ratio(r.p50, b.p50, 2),
                f"{fmt(b.p99)}, {fmt(e.p99)}, {fmt(r.p99)}",
            )
            for key, stats in (("binary", b), ("opcua_event", e), ("opcua_by_id", r)):
                section.value(f"{name}_{key}_p50_ms", stats.p50)
                section.value(f"{name}_{key}_p99_ms", stats.p99)
        section.tables.append(table)
        if mqtt_port is None:
            section.notes.append(
                "MQTT not measured: Debian's mosquitto is not installed "
                "(scripts/mosquitto_setup.sh installs it)."
            )
        else:
            seconds = 5.0 if not cfg.quick else 0.5
            answered, received, delays = asyncio.run(
                _mqtt_rates(server.port, mqtt_port, seconds, clients=4)
            )
            d = Stats.of(delays) if delays else None
            mqtt = Table(
                [
                    "binary results answered /s",
                    "MQTT result messages received /s",
                    "received / answered",
                    "RESULT → MQTT arrival p50 ms",
                    "p99 ms",
                ],
                caption=(
                    f"brightness, 4 binary-protocol clients for {seconds:g} s; one subscriber, "
                    "QoS 1, Mosquitto on loopback"
                ),
            )
            mqtt.add(
                f"{answered:.0f}",
                f"{received:.0f}",
                ratio(received, answered, 2),
                fmt(d.p50) if d else "-",
                fmt(d.p99) if d else "-",
            )
            section.tables.append(mqtt)
            section.value("mqtt_answered_per_s", answered)
            section.value("mqtt_received_per_s", received)
            section.goals.append(
                Goal(
                    "MQTT keeps up with the binary protocol: every result published, at the "
                    "rate the server answers",
                    f"{received / answered:.2f}x ({received:.0f}/s received, {answered:.0f}/s "
                    "answered)",
                    received >= 0.95 * answered,
                )
            )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(1, len(samples), figsize=(5.0 * len(samples), 3.4))
        for ax, (name, got) in zip(axes, samples.items(), strict=True):
            cdf(ax, got["binary"], "binary INSPECT")
            cdf(ax, got["opcua_event"], "OPC UA StartSingleJob → ResultReadyEvent")
            cdf(ax, got["opcua_by_id"], "OPC UA StartSingleJob → GetResultById")
            log_scale_if_positive(ax, "x")
            ax.set_xlabel(f"{name}: trigger to result [ms]")
            ax.set_ylabel("fraction of triggers")
            ax.legend(loc="lower right", fontsize=7)
        return [save(fig, directory / "plant.png")]

    section.plot = plot
    section.notes.append(
        "The same inspection of the same server each way: capture from the folder camera, the "
        "analysis, the result log (SQLite). OPC UA adds a method call (StartSingleJob answers "
        "before the job runs) and then either an event through the client's subscription or a "
        "second method call that waits for the result; every message is signed and encrypted."
    )
    return section
