"""20. OPC UA (OPC 40100-1): trigger to result, beside the binary protocol.

One ``vision-server serve`` process (its own, with this section's configuration) serves the
1024x768 server camera of section 2e (a folder camera replaying the tool camera's view of the
conveyor) with ``cap_locate`` (tens of ms) and ``brightness`` (well under a millisecond of
compute, so that a front-end's own cost shows), with the OPC UA front-end enabled.

- **OPC UA**: asyncua's client in a SignAndEncrypt session (Basic256Sha256, a user and
  password), as an MES would run a job: ``StartSingleJob`` then the ``ResultReadyEvent`` of its
  subscription (publishing interval ``EVENT_INTERVAL_MS``), and ``StartSingleJob`` then
  ``GetResultById(JobId)`` asked again at once while it answers Processing (a whole job
  without a subscription). Alternated with the binary protocol's ``INSPECT`` of the same
  inspection (no image: the server's camera), request by request, so that all share the
  machine's load.

MQTT's publish rate beside the binary protocol's is section 2f.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import yaml

from .busy import make_client
from .common import RunConfig, Section, Stats, Table, fmt, ratio
from .env import Env
from .line import _free_port
from .line import write_config as write_line_config
from .plots import cdf, log_scale_if_positive, pyplot, save

NAME = "plant"
TITLE = "20. OPC UA (OPC 40100-1): trigger to result, beside the binary protocol"
INSPECTIONS = ("brightness", "cap_locate")
EVENT_INTERVAL_MS = 0
"""The subscription's publishing interval asked for (0: the server's fastest)."""
OPERATOR = ("operator", "bench-operator-token")
MV = "http://opcfoundation.org/UA/MachineVision"
CELL = "urn:cellvision:opcua"


def write_config(workdir: Path, opcua_port: int) -> Path:
    """Section 2e's cell with OPC UA enabled."""
    path = write_line_config(workdir, _free_port())
    doc: dict[str, Any] = yaml.safe_load(path.read_text(encoding="utf-8"))
    doc["line"] = {"enabled": False}
    # The result log on, as in a plant: every job writes its row.
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
                while True:  # Processing (2) until the job has its result
                    _handle, result, _error = await results.call_method(
                        by_id, ua.ResultIdDataType(Id=job.Id), ua.Variant(0, ua.VariantType.Int32)
                    )
                    if result.ResultState != 2:
                        break
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


# ---------------------------------------------------------------------------- the section


def run(cfg: RunConfig, env: Env) -> Section:
    from robot_client.demo.cell import vision_server

    repeat = cfg.n(200, 5)
    warmup = cfg.n(20, 2)
    section = Section(NAME, TITLE, intro=(__doc__ or "").split("\n\n", 1)[1].strip())
    opcua_port = _free_port()
    config = write_config(cfg.workdir, opcua_port)
    table = Table(
        [
            "inspection",
            "binary INSPECT p50 ms",
            "OPC UA start → event p50 ms",
            "OPC UA start → GetResultById (polled) p50 ms",
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
    with vision_server(config, cfg.workdir / "server-plant.log") as server:
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

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(1, len(samples), figsize=(5.0 * len(samples), 3.4))
        for ax, (name, got) in zip(axes, samples.items(), strict=True):
            cdf(ax, got["binary"], "binary INSPECT")
            cdf(ax, got["opcua_event"], "OPC UA StartSingleJob → ResultReadyEvent")
            cdf(ax, got["opcua_by_id"], "OPC UA StartSingleJob → GetResultById, polled")
            log_scale_if_positive(ax, "x")
            ax.set_xlabel(f"{name}: trigger to result [ms]")
            ax.set_ylabel("fraction of triggers")
            ax.legend(loc="lower right", fontsize=7)
        return [save(fig, directory / "plant.png")]

    section.plot = plot
    section.notes.append(
        "The same inspection of the same server each way: capture from the folder camera, the "
        "analysis, the result log (SQLite). OPC UA adds a method call (StartSingleJob answers "
        "before the job runs) and then either an event through the client's subscription "
        "(publishing interval 0: sent as it is fired) or GetResultById asked again while it "
        "answers Processing; every message is signed and encrypted."
    )
    return section
