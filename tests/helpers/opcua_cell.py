"""A cell with the OPC UA front-end enabled, and asyncua's own client signed in to it over a
SignAndEncrypt session (docs/opcua.md), for the OPC UA tests."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from asyncua import Client, Node, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import (
    SecurityPolicyAes128Sha256RsaOaep,
    SecurityPolicyAes256Sha256RsaPss,
    SecurityPolicyBasic256Sha256,
)
from cryptography.x509.oid import ExtendedKeyUsageOID

from vision_server.app import App
from vision_server.service import CellRuntime

MV = "http://opcfoundation.org/UA/MachineVision"
CELL = "urn:cellvision:opcua"
OPERATOR = ("operator", "op-secret-123")
INTEGRATOR = ("integrator", "int-secret-456")
MEAN = 100
"""The grey level of the folder camera's image: ``bright`` passes, ``dark`` fails."""
CLIENT_URI = "urn:cellvision:test:client"
PROCESSING = 2
"""ResultStateDataType: not finished yet."""

CONFIG = """\
server: {port: 0, workers: 2, operator_token: op-secret-123, integrator_token: int-secret-456}
results: {enabled: false}
cameras:
  shelf: {source: folder, path: imgs}
  tool: {source: request}
inspections:
  - name: bright
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
  - name: dark
    type: presence
    camera: shelf
    measure: mean_intensity
    max: 10
  - name: from_robot
    type: presence
    camera: tool
    measure: mean_intensity
    min: 10
opcua: {enabled: true, port: 0, pki: pki, trust_all_clients: true OPCUA_EXTRA}
"""

POLICIES = {
    "Basic256Sha256": SecurityPolicyBasic256Sha256,
    "Aes128_Sha256_RsaOaep": SecurityPolicyAes128Sha256RsaOaep,
    "Aes256_Sha256_RsaPss": SecurityPolicyAes256Sha256RsaPss,
}


def write_cell(folder: Path, config: str = CONFIG, extra: str = "") -> Path:
    """The cell's files in ``folder``: an image for the folder camera and ``cell.yaml``
    (``extra``: more ``opcua:`` keys, each starting with ", ")."""
    (folder / "imgs").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "imgs" / "a.png"), np.full((48, 64), MEAN, np.uint8))
    path = folder / "cell.yaml"
    path.write_text(config.replace(" OPCUA_EXTRA", extra), encoding="utf-8")
    return path


@contextlib.asynccontextmanager
async def serving(path: Path) -> AsyncIterator[App]:
    runtime = CellRuntime(path)
    app = App(
        runtime.catalog,
        runtime.config.server,
        results=runtime.results,
        reloader=runtime.reload,
        opcua=runtime.config.opcua,
    )
    try:
        async with app:
            yield app
    finally:
        runtime.close()


async def client_certificate(folder: Path, uri: str = CLIENT_URI) -> tuple[Path, Path]:
    """A client application certificate and key (made once per folder)."""
    folder.mkdir(parents=True, exist_ok=True)  # noqa: ASYNC240 (a test's own folder)
    cert, key = folder / "client.der", folder / "client-key.pem"
    await setup_self_signed_certificate(
        key, cert, uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "test"}
    )
    return cert, key


RESULT_READY = 1024
"""ResultReadyEventType's NodeId in OPC 40100-1's namespace."""


class Events:
    """ResultReadyEvents as asyncua's subscription hands them over."""

    def __init__(self) -> None:
        self.queue: asyncio.Queue[Any] = asyncio.Queue()

    def event_notification(self, event: Any) -> None:
        self.queue.put_nowait(event)

    async def next(self) -> Any:
        return await asyncio.wait_for(self.queue.get(), 15)


@dataclass
class Vision:
    """A signed-in client and the VisionSystem's nodes it uses."""

    client: Client
    mv: int
    cell: int
    system: Node
    states: Node
    automatic: Node
    results: Node

    async def result_events(self, source: Node | None = None, interval_ms: float = 0) -> Events:
        """ResultReadyEvents of ``source`` (default the VisionSystem), in a new subscription."""
        events = Events()
        subscription = await self.client.create_subscription(interval_ms, events)
        await subscription.subscribe_events(source or self.system, ua.NodeId(RESULT_READY, self.mv))
        return events

    async def state(self) -> tuple[str, str]:
        vision = await (await self.states.get_child("0:CurrentState")).read_value()
        automatic = await (await self.automatic.get_child("0:CurrentState")).read_value()
        return vision.Text or "", automatic.Text or ""

    async def start_job(self, recipe: str, meas: str = "", part: str = "") -> str:
        out = await self.automatic.call_method(
            f"{self.mv}:StartSingleJob",
            ua.MeasIdDataType(Id=meas),
            ua.PartIdDataType(Id=part),
            ua.RecipeIdExternalDataType(Id=recipe),
            ua.ProductIdDataType(Id=""),
            ua.Variant([], ua.VariantType.Variant),
        )
        job, error = out
        assert error == 0
        return str(job.Id)

    async def result(self, result_id: str, within_s: float = 15.0) -> Any:
        """GetResultById, asked again while the job still runs (ResultState 2, Processing)."""
        async with asyncio.timeout(within_s):
            while True:
                out = await self.results.call_method(
                    f"{self.mv}:GetResultById",
                    ua.ResultIdDataType(Id=result_id),
                    ua.Variant(10_000, ua.VariantType.Int32),
                )
                _handle, result, error = out
                assert error == 0
                if result.ResultState != PROCESSING:
                    return result
                await asyncio.sleep(0.01)

    async def start_continuous(self, recipe: str) -> str:
        job, error = await self.automatic.call_method(
            f"{self.mv}:StartContinuous",
            ua.MeasIdDataType(Id=""),
            ua.PartIdDataType(Id=""),
            ua.RecipeIdExternalDataType(Id=recipe),
            ua.ProductIdDataType(Id=""),
            ua.Variant([], ua.VariantType.Variant),
        )
        assert error == 0
        return str(job.Id)

    async def call(self, node: Node, method: str, *args: Any) -> Any:
        return await node.call_method(f"{self.mv}:{method}", *args)


@contextlib.asynccontextmanager
async def signed_in(
    endpoint: str,
    certs: tuple[Path, Path],
    user: tuple[str, str] | None = OPERATOR,
    # None: the certificate is the user's identity too
    policy: str = "Basic256Sha256",
) -> AsyncIterator[Vision]:
    client = Client(endpoint, timeout=10)
    client.application_uri = CLIENT_URI
    await client.set_security(
        POLICIES[policy],
        str(certs[0]),
        str(certs[1]),
        mode=ua.MessageSecurityMode.SignAndEncrypt,
    )
    if user is not None:
        client.set_user(user[0])
        client.set_password(user[1])
    else:  # sign in with the application certificate as the user's (an X.509 identity token)
        await client.load_client_certificate(str(certs[0]))
        await client.load_private_key(str(certs[1]))
    async with client:
        await client.load_data_type_definitions()
        mv = await client.get_namespace_index(MV)
        cell = await client.get_namespace_index(CELL)
        system = await client.nodes.objects.get_child(f"{cell}:VisionSystem")
        states = await system.get_child(f"{mv}:VisionStateMachine")
        yield Vision(
            client,
            mv,
            cell,
            system,
            states,
            await states.get_child(f"{mv}:AutomaticModeStateMachine"),
            await system.get_child(f"{mv}:ResultManagement"),
        )
